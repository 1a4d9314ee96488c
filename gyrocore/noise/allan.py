"""Allan deviation and the IEEE Std 952 noise terms of a gyro, with confidence intervals.

What is here
------------
- :func:`identify_noise` / :func:`allan_analysis` — per axis: the overlapping Allan deviation
  (:func:`gyrocore.noise.adev.oadev`), chi-square confidence intervals from Greenhall's
  equivalent degrees of freedom, and the noise model — the terms of
  σ²(τ) = 3Q²/τ² + N²/τ + (2 ln2/π)B² + K²τ/3 + R²τ²/2 and a Gauss–Markov bias, fitted by the GMWM
  (:mod:`gyrocore.noise.gmwm`; or the IEEE 952 fits, :mod:`gyrocore.noise.ieee952`) after
  removing narrowband lines and the sensor's low-pass octaves (:mod:`gyrocore.noise.diagnostics`).
  The result of each axis carries a :class:`gyrocore.noise.model.NoiseModel`; a term the data
  cannot resolve (its 95 % interval reaches zero) is ``None`` in the JSON, not a guess.
- the motion gate of a noise record (:func:`analysed_span`: the whole record or its longest still
  stretch) and the record length a term needs (:func:`needed_duration_s`).

Conventions: rate signals are rad/s in the sensor frame S; the sample rate is the mean rate
(N−1)/duration and the sample index is the time base (bursty host timestamps of real logs
must not enter the Allan variance, DESIGN.md "Noise density convention").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace as _replace
from typing import Mapping, Sequence

import numpy as np
import scipy.linalg
import scipy.optimize
import scipy.stats

from gyrocore.errors import GyroInputError, warn_repair

from . import avar as AV, diagnostics, gmwm
from .adev import oadev, octave_m
from .ieee952 import ieee952_design, select_ieee952, term_interval
from .model import IEEE_TERMS, TERM_UNITS, TERMS, NoiseModel
from .options import DEFAULT_NOISE_OPTIONS, NoiseOptions
from gyrocore.data.checks import gap_threshold_s
from gyrocore.data.recording import AXES, GYRO_COLS, Recording
from gyrocore.data.still import StillGate, still_windows

__all__ = [
    "IEEE_TERMS",
    "TERM_UNITS",
    "AllanResult",
    "AllanAnalysis",
    "identify_noise",
    "needed_duration_s",
    "TERMS",
    "METHODS",
    "allan_analysis",
    "FORMAT_VERSION",
]

FORMAT_VERSION = "2.0"  # 2.0: GM terms, method, resolved flags, τ up to T/2
RAD2DEG = 180.0 / math.pi


# ---------------------------------------------------------------------------- results
@dataclass(frozen=True, eq=False)
class AllanResult:
    """The noise identification of one axis: its noise model and the estimator's diagnostics.

    Attributes
    ----------
    axis : str
        ``"x"``, ``"y"`` or ``"z"`` (sensor frame S).
    signal : str
        ``"gyro"`` (units rad/s) or ``"accel"`` (units m/s², then read every ``rad`` in the
        term names as ``m/s``).
    model : NoiseModel
        The identified terms of this axis (:class:`gyrocore.noise.model.NoiseModel`, one axis):
        values, 95 % intervals (``model.ci95``; [0, upper bound] when unresolved) and ``resolved``
        flags; :meth:`all_terms` gives the JSON values (None = unresolved).
    taus_s : ndarray, shape (M,)
        Averaging times, s.
    adev_rad_s : ndarray, shape (M,)
        Overlapping Allan deviation, rad/s.
    adev_ci95_rad_s : ndarray, shape (M, 2)
        95 % chi-square interval of the deviation (Greenhall EDF, SP 1065 eq. 45).
    edf : ndarray, shape (M,)
        Equivalent degrees of freedom used.
    fit_adev_rad_s : ndarray, shape (M,)
        Deviation of the fitted model at ``taus_s``.
    estimate : dict
        The fit's point estimate of every term (also the unresolved ones, for plotting / upper bounds).
    rate_hz : float
        Sample rate used (mean rate).
    n_samples : int
    """

    axis: str
    signal: str
    model: NoiseModel
    taus_s: np.ndarray
    adev_rad_s: np.ndarray
    adev_ci95_rad_s: np.ndarray
    edf: np.ndarray
    fit_adev_rad_s: np.ndarray
    estimate: Mapping[str, float] = field(default_factory=dict)
    rate_hz: float = float("nan")
    n_samples: int = 0
    method: str = "gmwm"
    chi2: float = float("nan")
    dof: int = 0
    #: terms of the fitted model (``estimate``) not resolved because a stand-in with a higher
    #: penalty fits as well: {term: stand-in} (``gmwm`` only)
    ambiguous: Mapping[str, str] = field(default_factory=dict)
    #: deviation of the sum of the REPORTED terms, rad/s, at ``taus_s``: resolved terms and
    #: terms fitted but not told from a stand-in (``ambiguous``); unresolved (null) terms left out.
    #: ``fit_adev_rad_s`` is the selected fit (the same unless the selection kept a null term)
    reported_adev_rad_s: np.ndarray | None = None
    #: shortest τ of the fit, s: shorter τ are shaped by the sensor's low-pass and not fitted
    #: (:func:`gyrocore.noise.diagnostics.bandwidth_start`)
    fit_from_tau_s: float = float("nan")
    #: goodness of fit of the selected model on the fitted scales (:func:`gyrocore.noise.diagnostics.goodness_of_fit`):
    #: ok, p_value, stat, dof, misses (points outside their 95 % interval), points, p_misses, z
    fit_check: Mapping[str, object] = field(default_factory=dict)
    #: narrowband lines found and removed before the fit (:func:`gyrocore.noise.diagnostics.line_avar`): Hz, rms
    #: (signal units) and their deviation at ``taus_s``
    lines_hz: tuple[float, ...] = ()
    lines_rms: tuple[float, ...] = ()
    lines_adev_rad_s: np.ndarray | None = None
    #: unclaimed long-τ terms this record is too short to resolve at their fitted level
    #: (:func:`gyrocore.noise.gmwm.not_resolvable`): {term: {expected_z, threshold, record_s, needed_s}}
    not_resolvable: Mapping[str, Mapping[str, float]] = field(default_factory=dict)

    @property
    def fit_ok(self) -> bool | None:
        """Does the selected model fit the measured Allan variance (None: not checked)?"""
        return self.fit_check.get("ok") if self.fit_check else None

    def terms(self) -> dict[str, float | None]:
        """The five IEEE terms of the model as DESIGN.md's JSON dict (None = unresolved)."""
        return {k: self.model.reported(k)[0] for k in IEEE_TERMS}

    def all_terms(self) -> dict[str, float | None]:
        """The five IEEE terms and the Gauss–Markov pair of the model (None = unresolved / absent)."""
        return {k: self.model.reported(k)[0] for k in TERMS}

    def interval(self, name: str) -> tuple[float, float]:
        """95 % interval (lo, hi) of a term of the model; [0, upper bound] when unresolved."""
        lo, hi = self.model.ci95[name][0]
        return float(lo), float(hi)

    def to_json(self) -> dict:
        """The DESIGN.md keys (+ ``correlated_sigma_rad_s``, ``correlated_tau_c_s``), ``ci95``, ``estimate``, the curve."""
        out: dict = self.all_terms()
        out["method"] = self.method
        out["resolved"] = {k: bool(v[0]) for k, v in self.model.resolved.items()}
        out["ci95"] = {k: [float(a), float(b)] for k, (a, b) in ((k, v[0]) for k, v in self.model.ci95.items())}
        out["estimate"] = dict(self.estimate)
        out["units"] = dict(TERM_UNITS)
        out["chi2"] = self.chi2
        out["dof"] = self.dof
        out["ambiguous"] = dict(self.ambiguous)
        out["not_resolvable"] = {k: dict(v) for k, v in self.not_resolvable.items()}
        if self.fit_check:
            out["fit_ok"] = bool(self.fit_check["ok"])
            out["fit_check"] = {k: v for k, v in self.fit_check.items() if k != "z"} | {
                "fitted_from_tau_s": self.fit_from_tau_s
            }
        if self.method != "adev_legacy":
            out["lines"] = [{"freq_hz": fq, "rms": a} for fq, a in zip(self.lines_hz, self.lines_rms)]
        out["curve"] = {
            "taus_s": self.taus_s,
            "adev_rad_s": self.adev_rad_s,
            "adev_ci95_rad_s": self.adev_ci95_rad_s,
            "edf": self.edf,
            "fit_adev_rad_s": self.fit_adev_rad_s,
        }
        if self.reported_adev_rad_s is not None:
            out["curve"]["reported_adev_rad_s"] = self.reported_adev_rad_s
        if self.fit_check:
            out["curve"]["fit_z"] = list(self.fit_check["z"])
        return out


@dataclass(frozen=True, eq=False)
class AllanAnalysis:
    """Allan results of a recording, per axis, plus what was used.

    Attributes
    ----------
    axes : dict[str, AllanResult]
        Gyro axes analysed.
    accel : dict[str, AllanResult]
        Accelerometer axes (only when requested and present), units m/s² instead of rad/s.
    rate_hz : float
        Mean sample rate (N−1)/duration, Hz.
    n_samples : int
    duration_s : float
    dropped_taus_s : tuple of float
        Requested averaging times that the recording was too short for.
    format_version : str
    """

    axes: Mapping[str, AllanResult]
    rate_hz: float
    n_samples: int
    duration_s: float
    accel: Mapping[str, AllanResult] = field(default_factory=dict)
    dropped_taus_s: tuple[float, ...] = ()
    format_version: str = FORMAT_VERSION
    method: str = "gmwm"
    still_fraction: float | None = None
    #: (t_first_s, t_last_s) of the still stretch analysed when the record held motion, else None
    analysed_span_s: tuple[float, float] | None = None

    def noise_model(self, axes: Sequence[str] | None = None) -> NoiseModel:
        """The gyro axes' noise models as one :class:`~gyrocore.noise.model.NoiseModel`; with
        ``axes`` (e.g. x, y, z for a budget), an axis not analysed takes the mean of the others."""
        m = NoiseModel.stack([r.model for r in self.axes.values()])
        return m if axes is None else m.complete(axes)

    def to_json(self) -> dict:
        out = {
            "method": self.method,
            "still_fraction": self.still_fraction,
            "analysed_span_s": None if self.analysed_span_s is None else list(self.analysed_span_s),
            "axes": {a: r.to_json() for a, r in self.axes.items()},
            "rate_hz": self.rate_hz,
            "n_samples": self.n_samples,
            "duration_s": self.duration_s,
            "dropped_taus_s": list(self.dropped_taus_s),
            "format_version": self.format_version,
        }
        if self.accel:
            out["accel_axes"] = {a: r.to_json() for a, r in self.accel.items()}
        return out


METHODS = ("gmwm", "adev", "adev_legacy")


#: Models the random-walk check applies to (``NoiseOptions.rw_check``, off by default: see there)
_RW_CHECK_MODELS = {"quantization_rad", "arw_rad_per_sqrt_s", "rrw_rad_per_s_sqrt_s"}


def _random_walk_check(f, omega: np.ndarray, rate_hz: float, tau_max_s: float, *, low_pass: bool, on: bool):
    """K claimed by the GMWM selection, tested against a GM that turns over inside the record.

    Applies where the selected model is K with white rate noise (and white angle noise or the
    low-pass deficit): the block-mean likelihood of :mod:`gyrocore.noise.rwgm` holds those terms
    exactly; a flicker floor (long memory) has no finite block-mean autocovariance there, so a
    model with B is left to the Allan-variance checks. When the GM world is not rejected at 5 %,
    K stays in the fitted model (its estimate, the fitted sum, N) but is reported null with its
    upper bound and ``ambiguous: {K: GM}`` — as a flicker floor not told from a GM.
    """
    from . import rwgm

    k = "rrw_rad_per_s_sqrt_s"
    if (
        not on
        or not f.method.startswith("gmwm")
        or f.all_terms()[k] is None
        or "correlated_sigma_rad_s" not in f.model.ci95
        or not set(f.selected) <= _RW_CHECK_MODELS
    ):
        return f
    chk = rwgm.random_walk_check(
        omega,
        rate_hz,
        arw_rad_per_sqrt_s=float(f.estimate["arw_rad_per_sqrt_s"]),
        quantization_rad=0.0 if low_pass else float(f.estimate["quantization_rad"]),
        tau_max_s=float(tau_max_s),
    )
    if chk is None or chk.claimed:
        return f
    terms = {**f.all_terms(), k: None}
    ci = {n: f.interval(n) for n in f.model.ci95}
    ci[k] = (0.0, ci[k][1])
    ambiguous = {**dict(f.ambiguous), k: "correlated_sigma_rad_s"}
    model = NoiseModel.identified(f.model.axes[0], terms, ci, ambiguous, f.estimate)
    return _replace(f, model=model, ambiguous=ambiguous)


def _axis_result(
    omega: np.ndarray,
    rate_hz: float,
    m: np.ndarray,
    *,
    axis: str,
    signal: str,
    engine: str,
    method: str = "gmwm",
    options: NoiseOptions = DEFAULT_NOISE_OPTIONS,
) -> AllanResult:
    if not np.all(np.isfinite(omega)):
        raise GyroInputError(f"{signal} axis {axis}: non-finite samples; drop or repair them before Allan analysis")
    taus, dev, ns = oadev(omega, rate_hz, m, engine=engine)
    if not np.all(dev > 0):
        raise GyroInputError(f"{signal} axis {axis}: constant signal (zero Allan deviation), nothing to identify")
    if method == "adev_legacy":
        return _legacy_result(omega, rate_hz, m, taus, dev, axis=axis, signal=signal, method=method)
    return _gmwm_result(omega, rate_hz, m, taus, dev, axis=axis, signal=signal, method=method, options=options)


def _remove_lines(omega, rate_hz, m, taus, dev, *, axis: str, signal: str):
    """The Allan variance less that of the narrowband lines (vibration, interference: not sensor
    noise; one warning naming them), and the lines (:func:`gyrocore.noise.diagnostics.line_avar`)."""
    avar = dev**2
    lines = diagnostics.line_avar(omega, rate_hz, m)
    if lines.freqs_hz:
        avar = np.maximum(avar - lines.avar, 0.05 * avar)
        warn_repair(
            f"{signal} axis {axis}: narrowband line(s) at "
            + ", ".join(f"{fq:.4g} Hz (rms {a:.2g})" for fq, a in zip(lines.freqs_hz, lines.rms))
            + " are not sensor noise: their Allan variance (up to "
            + f"{100 * float(np.max(lines.avar / dev**2)):.0f} % at tau = {taus[int(np.argmax(lines.avar / dev**2))]:.3g} s)"
            + " is removed before the noise fit"
        )
    return avar, lines


def _gmwm_result(omega, rate_hz, m, taus, dev, *, axis: str, signal: str, method: str, options: NoiseOptions):
    """One axis by the GMWM (or the joint IEEE 952 fit, ``adev``) on the line-free Allan variance
    above the sensor's low-pass, with the random-walk check, the goodness of fit and the sum of
    the reported terms."""
    n = int(omega.shape[0])
    avar, lines = _remove_lines(omega, rate_hz, m, taus, dev, axis=axis, signal=signal)
    # the octaves shaped by the sensor's low-pass are left out of the fit
    k0 = diagnostics.bandwidth_start(avar, m, n, rate_hz)
    # above the cut the low-pass still leaves a −κN²/τ² deficit: fitted in place of Q ("+lp")
    meth = method + "+lp" if k0 else method
    f = gmwm.fit_noise(taus[k0:], avar[k0:], m[k0:], n, method=meth, options=options, axis=axis)
    f = _random_walk_check(f, omega, rate_hz, taus[-1], low_pass=bool(k0), on=options.rw_check)
    sel = [AV.LINEAR.index(k) for k in f.selected]
    chk = diagnostics.goodness_of_fit(avar[k0:], f.fit_avar, f.cov, f.edf, diagnostics.n_params(f.coef, f.tau_c_s, sel))
    fit_all = AV.term_avar(m, rate_hz, method=meth, tau_c_s=f.tau_c_s) @ f.coef
    edf = f.edf
    if k0:
        edf = AV.avar_covariance(m, n, rate_hz, f.coef, f.tau_c_s, np.where(fit_all > 0, fit_all, avar), method=meth)[1]
        warn_repair(
            f"{signal} axis {axis}: the Allan variance below tau = {taus[k0]:.3g} s is shaped by the sensor's "
            f"low-pass (over the first octave it falls to {avar[1] / avar[0]:.2f} of its value; white noise: 0.5): "
            f"the noise model is fitted from tau = {taus[k0]:.3g} s"
        )
    # the sum of what is reported: unresolved terms (null, bounds only) left out. A term fitted
    # but not told from a stand-in (``ambiguous``: reported as "fitted X, not told from Y") stays
    # in: the data reject the model without it, only its name is open (sunsided 10-min x: without
    # it the sum is 7 σ below the last points)
    c_rep = np.array(f.coef, float).copy()
    reported = f.all_terms()
    for i, name in enumerate(AV.LINEAR):
        if reported[name] is None and name not in f.ambiguous and not (k0 and i == 0):
            c_rep[i] = 0.0  # (the low-pass deficit, column 0 under "+lp", is N's shape)
    rep_all = AV.term_avar(m, rate_hz, method=meth, tau_c_s=f.tau_c_s) @ c_rep
    if not chk.ok:
        j = int(np.argmax(np.abs(chk.z)))
        warn_repair(
            f"{signal} axis {axis}: the fitted noise model does not fit its Allan variance (goodness of fit "
            f"p = {chk.p_value:.2g}; {chk.misses} of {chk.z.size} points outside their 95 % interval, worst "
            f"at tau = {taus[k0 + j]:.3g} s, {math.sqrt(avar[k0 + j] / f.fit_avar[j]):.2g}x the fitted "
            "deviation): its terms are not to be trusted"
        )
    lo_q = scipy.stats.chi2.ppf(0.025, edf)
    hi_q = scipy.stats.chi2.ppf(0.975, edf)
    ci_dev = np.column_stack([dev * np.sqrt(edf / hi_q), dev * np.sqrt(edf / lo_q)])
    names = TERMS if method == "gmwm" else IEEE_TERMS
    est = {k: float(f.estimate[k]) for k in names}
    model = f.model
    if k0:  # beside a low-pass, Q is not identified (its column is the filter's deficit)
        est["quantization_rad"] = 0.0
        ci = {k: f.interval(k) for k in names} | {"quantization_rad": (0.0, float("inf"))}
        terms = {**f.all_terms(), "quantization_rad": None}
        model = NoiseModel.identified(axis, terms, ci, f.ambiguous, est, names)
    return AllanResult(
        axis=axis,
        signal=signal,
        model=model,
        taus_s=taus,
        adev_rad_s=dev,
        adev_ci95_rad_s=ci_dev,
        edf=edf,
        fit_adev_rad_s=np.sqrt(np.maximum(fit_all, 0.0)),
        estimate=est,
        rate_hz=rate_hz,
        n_samples=int(omega.shape[0]),
        method=method,
        chi2=f.chi2,
        dof=f.dof,
        ambiguous=dict(f.ambiguous),
        not_resolvable={k: dict(v) for k, v in f.not_resolvable.items()},
        reported_adev_rad_s=np.sqrt(np.maximum(rep_all, 0.0)),
        fit_from_tau_s=float(taus[k0]),
        lines_hz=tuple(lines.freqs_hz),
        lines_rms=tuple(lines.rms),
        lines_adev_rad_s=np.sqrt(lines.avar),
        fit_check={
            "ok": chk.ok,
            "p_value": chk.p_value,
            "stat": chk.stat,
            "dof": chk.dof,
            "misses": chk.misses,
            "points": int(chk.z.size),
            "p_misses": chk.p_misses,
            "z": [float(v) for v in chk.z],
        },
    )


def _legacy_result(omega, rate_hz, m, taus, dev, *, axis: str, signal: str, method: str):
    """One axis by the earlier IEEE 952 fit with backward elimination (``adev_legacy``)."""
    n_phase = omega.shape[0] + 1
    fit, active, upper = select_ieee952(taus, dev**2, m, n_phase)
    lo_q = scipy.stats.chi2.ppf(0.025, fit.edf)
    hi_q = scipy.stats.chi2.ppf(0.975, fit.edf)
    ci_dev = np.column_stack([dev * np.sqrt(fit.edf / hi_q), dev * np.sqrt(fit.edf / lo_q)])
    fit_dev = np.sqrt(np.maximum(ieee952_design(taus) @ fit.coef, 0.0))
    terms: dict[str, float | None] = {}
    est: dict[str, float] = {}
    ci: dict[str, tuple[float, float]] = {}
    for i, name in enumerate(IEEE_TERMS):
        if name in active:
            c, lo, hi = term_interval(fit, i)
            est[name] = math.sqrt(max(c, 0.0))
            ci[name] = (math.sqrt(max(lo, 0.0)), math.sqrt(max(hi, 0.0)) if math.isfinite(hi) else float("inf"))
            terms[name] = est[name] if (c > 0 and lo > 0) else None
        else:
            est[name] = 0.0
            hi = upper.get(name, float("inf"))
            ci[name] = (0.0, math.sqrt(max(hi, 0.0)) if math.isfinite(hi) else float("inf"))
            terms[name] = None
    return AllanResult(
        axis=axis,
        signal=signal,
        model=NoiseModel.identified(axis, terms, ci, {}, est, IEEE_TERMS),
        taus_s=taus,
        adev_rad_s=dev,
        adev_ci95_rad_s=ci_dev,
        edf=fit.edf,
        fit_adev_rad_s=fit_dev,
        estimate=est,
        rate_hz=rate_hz,
        n_samples=int(omega.shape[0]),
        method=method,
        chi2=fit.chi2,
    )


def _check_timestamps(rec: Recording) -> float:
    """The sample rate of the index time base (one warning when the timestamps are irregular).

    Bursty host timestamps (median interval < ½ mean, largest > 4 × mean: samples read in bursts
    from a device that sampled them evenly) → the mean rate (N−1)/duration. Gaps (a few intervals
    > 1.5 × median: samples lost, logging paused, recordings appended) → the rate of the intervals
    that are not gaps: the mean rate would count the pause as sampled time (a 300-s pause in a
    450-s MPU-6050 log: 60 instead of 100 Hz, N 29 % high).
    """
    d = np.diff(rec.t_s)
    mean_rate = rec.rate_hz
    if d.size < 2:
        return mean_rate
    med = float(np.median(d))
    mean = rec.duration_s / (rec.n - 1)
    if not (med <= 0 or d.max() > 5 * mean or abs(med - mean) > 0.2 * mean or d.max() > 1.5 * med):
        return mean_rate
    bursty = med < 0.5 * mean and d.max() > 4.0 * mean
    gaps = d > gap_threshold_s(d, med)  # 1.5 × median on a clean clock; beyond a host clock's jitter
    if med > 0 and not bursty and gaps.any() and (~gaps).sum() >= 2:
        rate = float((~gaps).sum() / d[~gaps].sum())
        if abs(rate / mean_rate - 1.0) > 1e-3:
            warn_repair(
                f"timestamps have {int(gaps.sum())} gap(s) (longest {d.max():.4g} s; median dt {med * 1e3:.3g} ms): "
                f"Allan analysis joins the pieces on the sample index at the rate of the intervals without gaps, "
                f"{rate:.6g} Hz (the mean rate (N-1)/duration, {mean_rate:.6g} Hz, would count the gaps as sampled time)"
            )
        return rate
    warn_repair(
        f"timestamps are irregular (median dt {med * 1e3:.3g} ms, max {d.max() * 1e3:.3g} ms): "
        f"Allan analysis uses the sample index at the mean rate (N-1)/duration = {mean_rate:.6g} Hz"
    )
    return mean_rate


#: Largest fraction of 2-s windows the motion gate may refuse before the record is called non-static.
MAX_MOVING_FRACTION = 0.5


def _judged_windows(gyro, rate_hz: float, *, window_s: float = 2.0, max_windows: int = 200):
    """The still gate (:func:`gyrocore.data.still.still_windows`, variance statistic, α = 10⁻³
    per window) on up to ``max_windows`` whole ``window_s`` windows evenly spread over the record.

    The gate is blind to slow bias wander (B, K, GM change a 2-s window's variance by far less
    than its χ² spread). Judging a long record on 200 windows gives its still fraction with a
    binomial standard error ≤ 3.5 %, ample against the 50 % limit, at a cost of
    O(max_windows · window), not O(n); only those windows are read (``gyro`` an (N, 3) array or
    chunk source of the columns such as a :class:`gyrocore.data.spill.ColumnSpill`). None when the
    record is shorter than ten windows.
    """
    on_disk = hasattr(gyro, "block")
    src = gyro if on_disk else np.asarray(gyro, float)
    n = src.n if on_disk else src.shape[0]
    n_win = int(round(window_s * rate_hz))
    if n < 10 * max(n_win, 8):
        return None  # too short to judge
    W = n // n_win
    if W > max_windows:
        pick = np.linspace(0, W - 1, max_windows).round().astype(np.int64)
        if on_disk:  # the picked windows, read one at a time
            src = np.concatenate([src.block(GYRO_COLS, int(k) * n_win, (int(k) + 1) * n_win) for k in pick])
        else:
            src = src[(pick[:, None] * n_win + np.arange(n_win)[None, :]).ravel()]
    return still_windows(src, rate_hz, StillGate(window_samples=n_win, false_reject_rate=1e-3))


def _check_rest_noise(recording: Recording) -> None:
    """One warning when a record the motion gate calls still has a per-sample noise no MEMS gyro
    has at rest (> ``STILL_NOISE_SUSPECT_RAD_S`` = 0.05 rad/s on an axis): deg/s numbers under a
    rad/s header. The reader makes this check only when accel columns say the sensor is at rest;
    a gyro-only file (an MPU-6050's 0.1 deg/s read as 0.1 rad/s) reached the analysis silently
    with N 57x too large."""
    from gyrocore.data.checks import STILL_NOISE_SUSPECT_RAD_S, still_noise_rad_s

    g = np.asarray(recording.gyro_rad_s)
    noise = np.array([still_noise_rad_s(g[:, i]) for i in range(3)])
    if np.any(noise > STILL_NOISE_SUSPECT_RAD_S):
        warn_repair(
            f"the still record's per-sample noise ({', '.join(f'{v:.3g}' for v in noise)}) rad/s exceeds any MEMS "
            f"gyro at rest ({STILL_NOISE_SUSPECT_RAD_S} rad/s per sample): is it deg/s labelled rad/s (rename the "
            f"columns gyro_*_deg_s)? Numbers below are as read"
        )


#: A still stretch shorter than this is not analysed (ten 2-s gate windows: below it the
#: long-τ end of the Allan curve is a handful of averages, and no term beyond N is resolvable).
MIN_STILL_STRETCH_S = 20.0
#: Per-window false-reject rate of the strict gate that marks *motion* when the record is cut
#: to its still stretch: a window of a still sensor crosses it once in 10⁶, so a false reject
#: of the 10⁻³ gate (one window in a thousand) does not split a still record, while handling
#: (variance 10²–10⁶ × the noise's) is caught in any window it touches.
STRICT_FALSE_REJECT_RATE = 1e-6


@dataclass(frozen=True)
class StillSpan:
    """Where a recording is still, from the still gate (:mod:`gyrocore.data.still`) on every 2-s window.

    Attributes
    ----------
    start, stop : int
        Sample rows ``start:stop`` to analyse (the whole record when its rejected windows are as
        many as the gate's false-reject rate explains).
    still_fraction : float
        Fraction of the windows the 10⁻³ gate calls still (NaN: too short to judge).
    n_windows, n_rejected : int
    cut : bool
        True when the record was cut to its longest still stretch.
    message : str
        What was done, for a ``warning:`` line ('' when nothing was cut).
    """

    start: int
    stop: int
    still_fraction: float
    n_windows: int = 0
    n_rejected: int = 0
    cut: bool = False
    message: str = ""


def analysed_span(
    gyro_rad_s: np.ndarray, rate_hz: float, *, t0_s: float = 0.0, window_s: float = 2.0, false_reject_rate: float = 1e-3
) -> StillSpan:
    """The part of a record that a noise identification may use: all of it, or its longest still stretch.

    Every ``window_s`` window is judged by the still gate :func:`gyrocore.data.still.still_windows`
    (window variance against the χ² quantile of the record's own noise level, false-reject rate
    ``false_reject_rate`` per still window). When the number of
    rejected windows k is one the false-reject rate explains (binomial tail
    P(X ≥ k | W, α) ≥ 10⁻³), and so is the number over the strict gate
    (:data:`STRICT_FALSE_REJECT_RATE`: a single 2-s turn in a long still log is not a false
    reject), the whole record is used, as before. Otherwise the record holds
    motion, and a single moving window ruins an Allan variance (a 30 °/s hand turn is 10⁴ × the
    variance of an MPU-6050's noise): the analysis is cut to the longest run of windows that
    pass the strict gate (:data:`STRICT_FALSE_REJECT_RATE`), less one window at each end that
    borders motion (the window holding the start or end of the motion may pass the gate with
    part of it inside). More than :data:`MAX_MOVING_FRACTION` of the windows moving (the
    noise level, a quantile of the window variances, is then not the sensor's), or a stretch
    shorter than :data:`MIN_STILL_STRETCH_S`, is an error naming the longest still stretch.

    Parameters
    ----------
    gyro_rad_s : ndarray (N, 3)
        Rate samples, rad/s, sensor frame S, evenly spaced at ``rate_hz``.
    rate_hz : float
    t0_s : float
        Time of the first sample (for the messages), s.

    Raises
    ------
    GyroInputError
        Mostly moving, or no still stretch of :data:`MIN_STILL_STRETCH_S`.
    """
    x = np.asarray(gyro_rad_s, float)
    N = x.shape[0]
    n_win = int(round(window_s * rate_hz))
    if n_win < 8 or N < 2 * n_win:
        return StillSpan(0, N, float("nan"))
    sw = still_windows(x, rate_hz, StillGate(window_samples=n_win, false_reject_rate=false_reject_rate))
    W = sw.n_windows
    still = sw.still
    quiet = sw.still_at(STRICT_FALSE_REJECT_RATE)
    k = int(W - still.sum())
    k_strict = int(W - quiet.sum())
    frac = float(still.mean())
    # motion: more windows over the gate than its false-reject rate explains, or any window over
    # the strict gate that its 1e-6 rate does not explain (one 2-s turn in a 10-min log)
    if (k == 0 or scipy.stats.binom.sf(k - 1, W, false_reject_rate) >= 1e-3) and (
        k_strict == 0 or scipy.stats.binom.sf(k_strict - 1, W, STRICT_FALSE_REJECT_RATE) >= 1e-3
    ):
        return StillSpan(0, N, frac, W, k)
    # runs of quiet windows [a, b), less one window at an end that borders motion
    best = (0, 0)
    i = 0
    while i < W:
        if not quiet[i]:
            i += 1
            continue
        j = i
        while j < W and quiet[j]:
            j += 1
        a = i + (1 if i > 0 else 0)
        b = j - (1 if j < W else 0)
        if b - a > best[1] - best[0]:
            best = (a, b)
        i = j
    a, b = best
    moving = np.flatnonzero(~still)
    tw = n_win / rate_hz  # window length as cut, s
    where = f"first at t = {t0_s + moving[0] * tw:.4g} s, last ending t = {t0_s + (moving[-1] + 1) * tw:.4g} s"
    stop = N if b == W else b * n_win  # a still end keeps the samples after the last whole window
    desc = f"t = {t0_s + a * tw:.4g}-{t0_s + stop / rate_hz:.4g} s ({(stop - a * n_win) / rate_hz:.3g} s)"
    longest = f"the longest still stretch is {desc}" if b > a else "no still stretch"
    if (1.0 - frac) > MAX_MOVING_FRACTION or (stop - a * n_win) / rate_hz < MIN_STILL_STRETCH_S:
        raise GyroInputError(
            f"recording is not static: the motion gate rejects {100 * (1 - frac):.0f} % of its {window_s:g}-s windows "
            f"({where}) and {longest}; noise identification needs a still sensor for >= {MIN_STILL_STRETCH_S:g} s "
            f"(choose one with --t-from-s/--t-to-s)"
        )
    msg = (
        f"motion in {k} of {W} {window_s:g}-s windows ({where}; the gate's false-reject rate explains "
        f"{W * false_reject_rate:.2g}): noise identified on the longest still stretch, {desc}, {100 * (stop - a * n_win) / N:.0f} % of the record"
    )
    return StillSpan(a * n_win, stop, frac, W, k, True, msg)


def allan_analysis(
    recording: Recording,
    *,
    axes: Sequence[str] = AXES,
    max_tau_s: float | None = None,
    accel: bool = False,
    engine: str = "fast",
    method: str = "gmwm",
    check_static: bool = False,
    options: NoiseOptions = DEFAULT_NOISE_OPTIONS,
) -> AllanAnalysis:
    """Overlapping ADEV and the identified noise terms of a static recording, per axis.

    Parameters
    ----------
    recording : Recording
        A still recording (gyro in rad/s, sensor frame S). Timestamps are used only for the
        mean rate (N−1)/duration; bursty host timestamps trigger a one-line warning.
    axes : sequence of {"x", "y", "z"}
    max_tau_s : float, optional
        Largest averaging time. Default: the whole record (m ≤ (N−1)/2, octave steps) for
        ``gmwm``/``adev``; a quarter of it for ``adev_legacy``. A value beyond half the
        record drops those τ with a warning naming them.
    accel : bool
        Also analyse the accelerometer (needed for Kalibr's accelerometer entries).
    engine : {"fast", "allantools"}
        ADEV kernel, see :func:`oadev`.
    method : {"gmwm", "adev", "adev_legacy"}
        ``gmwm`` (default): :mod:`gyrocore.noise.gmwm` with Gauss–Markov terms; ``adev``: the IEEE 952
        joint fit on the same statistic and weights; ``adev_legacy``: the earlier fit
        (τ ≤ T/4, backward elimination), kept for the study's baseline.
    check_static : bool
        Refuse a recording whose motion gate rejects more than :data:`MAX_MOVING_FRACTION`
        of its 2-s windows (one ``error:`` line naming the fraction).
    options : NoiseOptions, optional
        How the GMWM fit decides (:class:`gyrocore.noise.options.NoiseOptions`; default the
        project's rule).

    Raises
    ------
    GyroInputError
        Too few samples for at least 4 octave-spaced τ, a bad axis name or method, or
        (``check_static``) a moving recording.
    """
    if method not in METHODS:
        raise GyroInputError(f"unknown noise method {method!r}; use gmwm or adev")
    bad = [a for a in axes if a not in AXES]
    if bad or not axes:
        raise GyroInputError(f"unknown axis {','.join(bad) or '(none)'}; use a comma list of x,y,z")
    n = recording.n
    rate = recording.rate_hz
    if not (n >= 2 and math.isfinite(rate) and rate > 0):
        raise GyroInputError("Allan analysis needs at least 2 samples with increasing timestamps")
    rate = _check_timestamps(recording)
    still = None
    span_s = None
    if check_static:
        sp = analysed_span(recording.gyro_rad_s, rate, t0_s=float(recording.t_s[0]))
        still = sp.still_fraction
        if sp.cut:
            warn_repair(sp.message)
            recording = recording.slice(sp.start, sp.stop)
            n = recording.n
            span_s = (float(recording.t_s[0]), float(recording.t_s[-1]))
        _check_rest_noise(recording)
    dropped: list[float] = []
    if max_tau_s is not None:
        if not (max_tau_s > 0):
            raise GyroInputError(f"--max-tau-s must be positive, got {max_tau_s}")
        want = octave_m(10**12, max_m=max(1, int(math.floor(max_tau_s * rate + 1e-9))))
        limit = (n - 1) // 2
        m = want[want <= limit]
        dropped = [float(mm / rate) for mm in want[want > limit]]
        if dropped:
            warn_repair(
                f"recording is {recording.duration_s:.4g} s long: dropped tau = "
                + ", ".join(f"{t:.4g}" for t in dropped)
                + f" s (overlapping ADEV needs tau <= T/2 = {limit / rate:.4g} s)"
            )
    elif method == "adev_legacy":
        m = octave_m(n)
    else:
        from .avar import scales

        m = scales(n)
    if m.size < 4 or octave_m(n).size < 4:
        raise GyroInputError(
            f"recording too short for Allan analysis: {n} samples ({recording.duration_s:.3g} s) "
            f"give {octave_m(n).size} averaging times, need at least 4 (>= {16 * 2 + 1} samples)"
        )

    def run(x, signal):
        return {
            a: _axis_result(
                x[:, AXES.index(a)], rate, m, axis=a, signal=signal, engine=engine, method=method, options=options
            )
            for a in axes
        }

    gyro = run(recording.gyro_rad_s, "gyro")
    acc: dict[str, AllanResult] = {}
    if accel:
        if recording.accel_m_s2 is None:
            raise GyroInputError("accelerometer Allan analysis requested but the file has no accel columns")
        acc = run(recording.accel_m_s2, "accel")
    if method != "adev_legacy":
        _warn_short(gyro, (n - 1) / rate, n, float(rate), method)
    return AllanAnalysis(
        axes=gyro,
        accel=acc,
        rate_hz=float(rate),
        n_samples=n,
        duration_s=(n - 1) / rate,  # sampled time on the index time base (= t span without gaps)
        dropped_taus_s=tuple(dropped),
        method=method,
        still_fraction=still,
        analysed_span_s=span_s,
    )


_LONG = {
    "bias_instability_rad_s": "B",
    "rrw_rad_per_s_sqrt_s": "K",
    "rate_ramp_rad_s2": "R",
    "correlated_sigma_rad_s": "GM",
}


def needed_duration_s(result: AllanResult, name: str, *, level_factor: float = 0.5, max_factor: int = 4096) -> float:
    """Record length at which term ``name`` at ``level_factor`` × its current 95 % upper bound would be
    resolvable (:func:`gyrocore.noise.gmwm.fisher_margin` ≥ 1.28: Fisher z against the term's absence,
    next to the resolved terms — no stand-in terms considered, so a lower bound on the length).

    Doubles the record length until the predicted margin of the term reaches the threshold; inf if
    not within ``max_factor`` × the present length. For GM the correlation time is the
    longest τ of the present record.
    """
    from .gmwm import Z_POWER, fisher_margin

    level = result.interval(name)[1] * level_factor if name in result.model.ci95 else float("nan")
    if not (math.isfinite(level) and 0 < level < 1e100):
        return float("nan")
    base = {k: v for k, v in result.all_terms().items() if v is not None}
    base[name] = level
    if name == "correlated_sigma_rad_s":
        base["correlated_tau_c_s"] = float(result.taus_s[-1])
    n = result.n_samples
    f = 1
    while f <= max_factor:
        z = fisher_margin(
            base, name, n_samples=n * f, rate_hz=result.rate_hz, method="adev" if result.method != "gmwm" else "gmwm"
        )
        if z >= Z_POWER:
            return n * f / result.rate_hz
        f *= 2
    return float("inf")


#: Below this record length, a record with no long-τ term resolved gets the one warning.
SHORT_RECORD_S = 1800.0


def _warn_short(axes: Mapping[str, AllanResult], duration_s: float, n: int, rate: float, method: str) -> None:
    """One warning when no long-τ term is resolved on any axis of a record shorter than
    :data:`SHORT_RECORD_S`: which terms need how long a record (at half their upper bound)."""
    if duration_s >= SHORT_RECORD_S or any(r.all_terms()[k] is not None for r in axes.values() for k in _LONG):
        return
    names = [k for k in _LONG if method == "gmwm" or k != "correlated_sigma_rad_s"]
    need = {}
    for k in names:
        vals = [needed_duration_s(r, k) for r in axes.values()]
        vals = [v for v in vals if math.isfinite(v)]
        if vals:
            need[k] = min(vals)

    def fmt(t):
        return f"{t / 3600:.3g} h" if t >= 7200 else (f"{t / 60:.3g} min" if t >= 120 else f"{t:.3g} s")

    parts = [f"{_LONG[k]} at half its upper bound needs >= {fmt(v)}" for k, v in need.items()]
    warn_repair(
        f"no long-tau term resolved in {fmt(duration_s)}: bias instability, random walks and correlated terms are "
        "null with 95 % upper bounds" + ("; " + ", ".join(parts) if parts else "")
    )


def identify_noise(
    data,
    *,
    rate_hz: float | None = None,
    method: str = "gmwm",
    axes: Sequence[str] | None = None,
    max_tau_s: float | None = None,
    signal: str = "gyro",
    check_static: bool = True,
    engine: str = "fast",
    options: NoiseOptions = DEFAULT_NOISE_OPTIONS,
) -> AllanAnalysis:
    """Identify the noise terms of a still recording or of rate arrays (the public API).

    Parameters
    ----------
    data : Recording or ndarray, shape (n,) or (n, k), k ≤ 3
        A :class:`~gyrocore.data.recording.Recording` (gyro rad/s in the sensor frame S; rate =
        its mean rate (N−1)/duration), or rate samples [rad/s] evenly spaced at ``rate_hz``
        (columns = axes x, y, z in order).
    rate_hz : float
        Sample rate, Hz; required for arrays, ignored for a Recording.
    method : {"gmwm", "adev"}
        ``gmwm`` (default, :mod:`gyrocore.noise.gmwm`): Q, N, B, K, R and one Gauss–Markov term;
        ``adev``: the IEEE 952 joint fit (no GM).
    axes : sequence of {"x", "y", "z"}, optional
        Default: all columns.
    max_tau_s : float, optional
    signal : {"gyro", "accel"}
        Which signal of a Recording (accel: units m/s², read rad as m/s in the term names).
    check_static : bool
        Refuse non-static data (motion gate, see :func:`allan_analysis`).
    options : NoiseOptions, optional
        How the GMWM fit decides (:class:`gyrocore.noise.options.NoiseOptions`).

    Returns
    -------
    AllanAnalysis
        Frozen; ``.axes[a]`` is an :class:`AllanResult` whose ``model`` holds every term (None =
        not resolved in :meth:`AllanResult.all_terms`), its 95 % intervals ([0, upper bound] when
        unresolved) and ``resolved`` flags, its ``.estimate`` and ADEV curves; ``.noise_model()`` the
        axes' models as one.
    """
    if isinstance(data, Recording):
        rec = data
        if signal == "accel":
            if rec.accel_m_s2 is None:
                raise GyroInputError("accelerometer noise requested but the recording has no accel columns")
            rec = Recording(t_s=rec.t_s, gyro_rad_s=rec.accel_m_s2)
        elif signal != "gyro":
            raise GyroInputError(f"signal must be 'gyro' or 'accel', got {signal!r}")
        ax = tuple(axes) if axes is not None else AXES
    else:
        x = np.asarray(data, dtype=float)
        if x.ndim == 1:
            x = x[:, None]
        if x.ndim != 2 or not (1 <= x.shape[1] <= 3):
            raise GyroInputError(f"rate array must have shape (n,) or (n, k<=3), got {np.shape(data)}")
        if rate_hz is None or not (math.isfinite(float(rate_hz)) and float(rate_hz) > 0):
            raise GyroInputError("identify_noise on an array needs rate_hz > 0")
        return _identify_arrays(
            x,
            float(rate_hz),
            method=method,
            axes=axes,
            max_tau_s=max_tau_s,
            check_static=check_static and x.shape[1] == 3,
            engine=engine,
            options=options,
        )
    return allan_analysis(
        rec, axes=ax, max_tau_s=max_tau_s, engine=engine, method=method, check_static=check_static, options=options
    )


def _identify_arrays(
    x: np.ndarray,
    rate: float,
    *,
    method: str,
    axes,
    max_tau_s,
    check_static: bool,
    engine: str,
    options: NoiseOptions = DEFAULT_NOISE_OPTIONS,
) -> AllanAnalysis:
    """:func:`identify_noise` on evenly spaced rate columns without building a Recording (no copy
    of the record, no timestamp checks: the spacing is 1/rate by definition)."""
    if method not in METHODS:
        raise GyroInputError(f"unknown noise method {method!r}; use gmwm or adev")
    n, k = x.shape
    names = AXES[:k]
    ax = tuple(axes) if axes is not None else names
    bad = [a for a in ax if a not in names]
    if bad or not ax:
        raise GyroInputError(f"unknown axis {','.join(bad) or '(none)'} for {k} column(s)")
    still = None
    if check_static:
        sw = _judged_windows(x, rate)
        still = sw.fraction if sw is not None else float("nan")
        if math.isfinite(still) and (1.0 - still) > MAX_MOVING_FRACTION:
            raise GyroInputError(
                f"recording is not static: the motion gate rejects {100 * (1 - still):.0f} % of its 2-s windows "
                f"(more than {100 * MAX_MOVING_FRACTION:.0f} %); noise identification needs a still sensor"
            )
    from .avar import scales

    if max_tau_s is not None:
        if not (max_tau_s > 0):
            raise GyroInputError(f"max_tau_s must be positive, got {max_tau_s}")
        m = scales(n, max_m=max(1, int(math.floor(max_tau_s * rate + 1e-9))))
    else:
        m = octave_m(n) if method == "adev_legacy" else scales(n)
    if m.size < 4 or octave_m(n).size < 4:
        raise GyroInputError(
            f"recording too short for Allan analysis: {n} samples give {octave_m(n).size} averaging times, "
            f"need at least 4 (>= {16 * 2 + 1} samples)"
        )
    res = {
        a: _axis_result(
            np.ascontiguousarray(x[:, names.index(a)]),
            rate,
            m,
            axis=a,
            signal="gyro",
            engine=engine,
            method=method,
            options=options,
        )
        for a in ax
    }
    duration = (n - 1) / rate
    if method != "adev_legacy":
        _warn_short(res, duration, n, rate, method)
    return AllanAnalysis(axes=res, rate_hz=rate, n_samples=n, duration_s=duration, method=method, still_fraction=still)
