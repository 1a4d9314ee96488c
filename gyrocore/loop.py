"""The residual loop: find what the model still leaves, name the effect, add it, refit.

Start from the declared effects, fit them jointly to the residual of
:mod:`gyrocore.residual` (whatever reference the data offer), then repeat:

1. **Trace.** For every catalogue effect not yet in the model (each through its physical
   regressors from :func:`gyrocore.effects.design`, integrated over the observation windows),
   refit the model plus that candidate jointly (:func:`gyrocore.lsq.solve`) and test
   "candidate parameters = 0" with a Wald statistic on a **HAC** covariance — ``lsq``'s
   ``"hac"``: the sandwich with each axis' residual autocovariance (short-lag sample values
   plus a fitted Gauss–Markov tail), so that coloured residuals (on-chip low-pass, bias
   instability, rate random walk, an optical reference's noise) do not pass for a signal —
   referred to F(q, M − P) (q candidate parameters, M windows, P fitted parameters). With a
   known-angle reference the fit is weighted by the known uncertainties (OLS covariance).
2. **Select with false-discovery control.** Forward selection with Holm-type step-down
   thresholds: at a step with K testable candidates the smallest p-value must be below α/K
   (Holm 1979), so the family-wise error over candidates and steps stays ≤ α. The winner must
   also be of practical size: it must cut the window residual RMS by ``min_rms_reduction`` or
   the attitude error by ``min_attitude_reduction``, and it must hold *out of sample*: the
   model plus the candidate, refitted on every other tenth of the recording, must predict the
   remaining tenths better than the model alone, and vice versa (2-fold blocked; in-sample
   with fewer than 40 windows or a known-angle reference). Where a fold cannot identify the
   joint model (a rate table turning one axis and one sense at a time) the candidate's own
   columns, fitted to the current residual, must predict it instead. This guards
   against HAC's optimism on short, strongly coloured residuals: a ramp fitted to one stretch
   of flicker wander does not predict the next.
3. **Collinearity.** Every other candidate that also passes is tested again in the presence of
   the winner and vice versa; if neither adds anything once the other is in (e.g.
   ``bias_ramp`` vs ``bias_thermal`` when the temperature rises linearly in time) the step
   reports them as *ambiguous* (``evidence["ambiguous_with"]``); the winner stays the one
   with the strongest evidence (smallest p-value, which accounts for the number of
   parameters) unless another is within one decade of p, in which case the simpler effect is
   taken (fewer parameters, then the lower-order, more common one: earlier in
   :data:`CANDIDATES`). A candidate contained in the winner that explains the same residual
   replaces it (parsimony). A thermal candidate is tested on top of its constant companion
   (:data:`COMPANION`) and added with it.
4. **Add and refit** everything jointly, record the error before and after (windowed residual
   RMS, attitude error), and repeat until nothing significant is left. ``time_offset`` is
   re-linearised (Gauss–Newton): the gyro is advanced by the estimate (cubic spline) and the
   residual rebuilt, until the correction is below 1 µs — the first-order regressor −τ·dω/dt
   leaves a second-order term τ²/2·d²ω/dt² that fast motion would otherwise pass to scale-like
   candidates.

What remains is described by a Ljung–Box whiteness test, a Welch spectrum and the Allan
deviation of the final window residual (:class:`Remaining`).

The attitude error is always in-sample (the parameters are fitted on the same recording);
it is the integrated corrected gyro against the reference attitude (``rate``/``attitude``),
the integrated angle inside still segments (``still``), or the per-segment angle error
(``angles``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
from scipy import signal, stats

from . import effects as E
from . import lsq
from .attitude import error_angle_rad, integrate_gyro
from .errors import GyroInputError
from .recording import Recording
from .residual import Residual, Segment, build_residual

__all__ = [
    "CANDIDATES",
    "FITTABLE",
    "Evidence",
    "Step",
    "Remaining",
    "LoopResult",
    "run_loop",
    "loop_residual",
    "attitude_error_deg",
    "plot_found",
]

FORMAT_VERSION = "1.0"

#: Effects the loop can trace (each has linear regressors).
CANDIDATES: tuple[str, ...] = E.CORRECTABLE
FITTABLE = CANDIDATES

#: A thermal polynomial in (T − T0) with T0 ≠ the recording's mean temperature also shifts
#: the constant term, which belongs to ``bias``/``scale``: a thermal candidate is tested on top
#: of its constant companion (the test asks for more than a constant) and, when taken, is added
#: together with it.
COMPANION = {"bias_thermal": "bias", "scale_thermal": "scale"}


def _single_thread():
    """Limit BLAS to one thread: the fits are small (≤ 1500 windows × 40 columns), and on a
    loaded machine threaded BLAS is up to 50× slower than one thread."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - optional
        import contextlib

        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


@dataclass(frozen=True)
class Evidence:
    """Why an effect was (or was not) taken.

    Attributes
    ----------
    statistic : float
        Wald statistic / q on the HAC covariance (an F statistic).
    df1, df2 : int
        q (testable candidate parameters) and M − P.
    p_value : float
        P(F(df1, df2) > statistic).
    log10_p : float
        log10 of the p-value (finite where the p-value underflows).
    threshold : float
        Holm threshold α/K at this step.
    params : dict
        ``"param[index]"`` -> estimate, SI.
    std_errors : dict
        ``"param[index]"`` -> HAC standard error, SI.
    unobservable : tuple of str
        Candidate parameters the data cannot determine (not tested).
    rms_reduction : float
        1 − RMS(after)/RMS(before) of the window residual.
    attitude_reduction : float
        1 − error(after)/error(before) (NaN if no attitude error is defined).
    hac_bandwidth : float
        Bartlett bandwidth in windows.
    ambiguous_with : tuple of str
        Candidates that explain the same residual (see module docstring).
    cv_rms_reduction : float
        1 − RMS(with)/RMS(without the candidate) of the window residual predicted out of
        sample (2-fold blocked in time; see the module docstring); NaN when no fold split
        can identify the candidate (no verdict).
    """

    statistic: float
    df1: int
    df2: int
    p_value: float
    log10_p: float
    threshold: float
    params: dict
    std_errors: dict
    unobservable: tuple[str, ...]
    rms_reduction: float
    attitude_reduction: float
    hac_bandwidth: float
    ambiguous_with: tuple[str, ...] = ()
    cv_rms_reduction: float = float("nan")

    @property
    def significant(self) -> bool:
        return self.df1 > 0 and self.p_value < self.threshold


@dataclass(frozen=True)
class Step:
    """One loop step: the effect added and the error before and after."""

    effect: str
    evidence: Evidence
    residual_rms_before_rad_s: float
    residual_rms_after_rad_s: float
    attitude_error_before_deg: float
    attitude_error_after_deg: float


@dataclass(frozen=True, eq=False)
class Remaining:
    """What the final residual still holds.

    The Ljung–Box test uses all windows; the Welch spectrum and the Allan deviation use the
    longest run of evenly spaced windows (empty when it is shorter than 17 windows).

    Attributes
    ----------
    ljung_box_p : float
        Ljung–Box p-value over 3 axes (small = not white).
    window_s : float
        Median window length, s (the residual's sample interval for the spectrum/Allan).
    welch_freq_hz : ndarray, shape (F,)
    welch_psd : ndarray, shape (F, 3)
        One-sided PSD of the window residual, (rad/s)²/Hz.
    allan_tau_s : ndarray, shape (K,)
    allan_adev_rad_s : ndarray, shape (K, 3)
    allan_slope : ndarray, shape (3,)
        Log-log slope of the Allan deviation (−½ white, 0 flicker, +½ RRW, +1 ramp).
    """

    ljung_box_p: float
    window_s: float
    welch_freq_hz: np.ndarray
    welch_psd: np.ndarray
    allan_tau_s: np.ndarray
    allan_adev_rad_s: np.ndarray
    allan_slope: np.ndarray

    def summary(self) -> dict:
        """JSON-friendly summary."""
        return {
            "ljung_box_p": self.ljung_box_p,
            "white": bool(np.isfinite(self.ljung_box_p) and self.ljung_box_p >= 0.01),
            "window_s": self.window_s,
            "welch_peak_hz": [float(self.welch_freq_hz[1:][np.argmax(self.welch_psd[1:, i])])
                              if self.welch_freq_hz.size > 2 else None for i in range(3)],
            "allan_tau_s": self.allan_tau_s,
            "allan_adev_rad_s": self.allan_adev_rad_s,
            "allan_slope": self.allan_slope,
        }


@dataclass(frozen=True, eq=False)
class LoopResult:
    """Result of :func:`run_loop` (JSON: :meth:`to_json`, DESIGN.md "JSON of loop").

    Attributes
    ----------
    declared : tuple of str
    found : tuple of Step
    reference : str
        Reference kind used.
    description : str
        The reference, one line.
    residual_rms_before_rad_s, residual_rms_after_rad_s : float
        RMS over windows and axes of the window residual with the declared model only / with
        declared + found, rad/s.
    attitude_error_before_deg, attitude_error_after_deg : float
        RMS attitude error (see module docstring), deg; NaN when not defined.
    params : dict
        Final joint fit: effect -> {"param[index]": [value, stderr]}, SI.
    tested : dict
        Last step's evidence of every candidate not taken.
    untestable : dict
        Candidate -> reason (missing column, not observable).
    remaining : Remaining
    notes : tuple of str
    n_windows : int
    alpha : float
    residual : Residual
        The residual the loop worked on (window regressors, for plots).
    history : tuple of ndarray, each (M, 3)
        Window residual with the declared model, then after each step, rad/s.
    """

    declared: tuple[str, ...]
    found: tuple[Step, ...]
    reference: str
    description: str
    residual_rms_before_rad_s: float
    residual_rms_after_rad_s: float
    attitude_error_before_deg: float
    attitude_error_after_deg: float
    params: dict
    tested: dict
    untestable: dict
    remaining: Remaining
    notes: tuple[str, ...]
    n_windows: int
    alpha: float = 0.01
    format_version: str = FORMAT_VERSION
    residual: Residual | None = field(default=None, repr=False)
    history: tuple = field(default=(), repr=False)

    @property
    def found_effects(self) -> list[str]:
        return [s.effect for s in self.found]

    def to_json(self) -> dict:
        """The DESIGN.md JSON (plus extra keys)."""

        def ev(e: Evidence) -> dict:
            return {
                "statistic": e.statistic, "df1": e.df1, "df2": e.df2, "p_value": e.p_value,
                "log10_p": e.log10_p, "threshold": e.threshold, "params": e.params,
                "std_errors": e.std_errors, "unobservable": list(e.unobservable),
                "rms_reduction": e.rms_reduction, "attitude_reduction": e.attitude_reduction,
                "hac_bandwidth_windows": e.hac_bandwidth, "ambiguous_with": list(e.ambiguous_with),
                "cv_rms_reduction": e.cv_rms_reduction,
            }

        return {
            "format_version": self.format_version,
            "declared": list(self.declared),
            "found": [
                {
                    "effect": s.effect,
                    "evidence": ev(s.evidence),
                    "residual_rms_before_rad_s": s.residual_rms_before_rad_s,
                    "residual_rms_after_rad_s": s.residual_rms_after_rad_s,
                    "attitude_error_before_deg": s.attitude_error_before_deg,
                    "attitude_error_after_deg": s.attitude_error_after_deg,
                }
                for s in self.found
            ],
            "residual_rms_before_rad_s": self.residual_rms_before_rad_s,
            "residual_rms_after_rad_s": self.residual_rms_after_rad_s,
            "attitude_error_before_deg": self.attitude_error_before_deg,
            "attitude_error_after_deg": self.attitude_error_after_deg,
            "reference": self.reference,
            "reference_description": self.description,
            "n_windows": self.n_windows,
            "alpha": self.alpha,
            "params": self.params,
            "not_taken": {k: ev(v) for k, v in self.tested.items()},
            "untestable": dict(self.untestable),
            "remaining": self.remaining.summary(),
            "notes": list(self.notes),
        }


# ---------------------------------------------------------------------------- internals
class _Model:
    """Stacked window regressors of a list of effects."""

    def __init__(self, res: Residual, orders: Mapping[str, int]):
        self.res = res
        self.orders = dict(orders)

    def block(self, effect: str) -> tuple[list[str], np.ndarray]:
        return self.res.regressors(effect, order=self.orders.get(effect, 1))

    def design(self, effects: Sequence[str]):
        cols, names, slices, p0 = [], [], {}, 0
        for e in effects:
            n, X = self.block(e)
            cols.append(X)
            names += [f"{e}.{c}" for c in n]
            slices[e] = slice(p0, p0 + X.shape[2])
            p0 += X.shape[2]
        if not cols:
            return np.zeros((self.res.m, 3, 0)), [], {}
        return np.concatenate(cols, axis=2), names, slices

    def fit(self, effects: Sequence[str]):
        """Joint fit; returns (LsqFit or None, window residual (M,3), theta per effect)."""
        y = self.res.y_rad_s
        if not effects:
            return None, y.copy()
        X, names, slices = self.design(effects)
        with np.errstate(invalid="ignore"):  # a negative HAC variance comes back as NaN = not testable
            if self.res.kind == "angles":
                # a few known angles among still windows: weighted least squares with the known
                # angle uncertainty on the rotation windows and the still windows' own scatter;
                # the covariance is s²(AᵀWA)⁻¹ (s² ≈ 1 when the weights are right)
                f = lsq.solve(y, X, names, slices, weights=self.angle_weights(), covariance="ols",
                              axis_weighting=False, on_unobservable="drop", min_excitation_snr=0.0)
            else:
                f = lsq.solve(y, X, names, slices, covariance="hac", on_unobservable="drop",
                              min_excitation_snr=0.0)
        return f, f.residual_rad_s

    def angle_weights(self) -> np.ndarray:
        """Row weights 1/σ² for the ``angles`` residual, (M, 3)."""
        if "angle_w" not in self.__dict__:
            res = self.res
            rot = res.is_rotation
            T = res.duration_s
            w = np.ones((res.m, 3))
            still = ~rot
            if still.sum() >= 3:
                sd = np.std(res.y_rad_s[still], axis=0, ddof=1)
                w[still] = 1.0 / np.maximum(sd, 1e-12) ** 2
            # per component: σ_i² = σ_angle²·u_i² + σ_across²·(1 − u_i²), u = φ/|φ|; an axis
            # error δ moves exp(φ) by 2|sin(φ/2)|·δ across the axis (nothing for whole turns):
            # σ_across = max(σ_angle, 2|sin(φ/2)|·σ_axis) (exact for rotations about a sensor axis)
            phi = res.angle_S_rad[rot] if res.angle_S_rad is not None else np.zeros((rot.sum(), 3))
            ang = np.linalg.norm(phi, axis=1)
            u2 = np.where(ang[:, None] > 0, (phi / np.where(ang > 0, ang, 1.0)[:, None]) ** 2, 1.0 / 3)
            s_across = np.maximum(res.angle_sigma_rad, 2 * np.abs(np.sin(ang / 2)) * res.axis_sigma_rad)
            if res.angle_mode == "axis":  # nothing known across the axis
                s_across = np.full_like(s_across, 1e6)
            var = res.angle_sigma_rad**2 * u2 + s_across[:, None] ** 2 * (1 - u2)
            w[rot] = T[rot, None] ** 2 / var
            self.angle_w = w
        return self.angle_w

    def correction(self, fit, effects: Sequence[str]) -> np.ndarray:
        """Per-sample correction Σ A_e·θ_e, rad/s, (N, 3)."""
        c = np.zeros((self.res.inputs.n, 3))
        if fit is None:
            return c
        for e in effects:
            c += self.res.sample_correction(e, fit.effect_theta(e), order=self.orders.get(e, 1))
        return c


def _cv_rms(y: np.ndarray, X: np.ndarray, *, min_windows: int = 40, n_blocks: int = 10) -> float:
    """Out-of-sample RMS of the window residual, 2-fold with blocks in time.

    The windows are cut into ``n_blocks`` contiguous blocks assigned alternately to two folds
    (so both folds span the whole recording — temperature range, ramp — while neighbouring,
    correlated windows stay together); each fold is predicted by the ordinary least-squares
    fit on the other. With fewer than ``min_windows`` windows the in-sample RMS is returned.
    y (M, 3), X (M, 3, P).
    """
    M = y.shape[0]
    if X.shape[2] == 0:
        return _rms(y)
    if M < min_windows:
        th, *_ = np.linalg.lstsq(X.reshape(-1, X.shape[2]), y.reshape(-1), rcond=None)
        return _rms(y - np.einsum("mip,p->mi", X, th))
    fold = (np.arange(M) * n_blocks // M) % 2 == 0
    Af = X.reshape(-1, X.shape[2])
    cf = np.linalg.norm(Af, axis=0)
    cf[cf == 0] = 1.0
    rank_full = np.linalg.matrix_rank(Af / cf, tol=1e-8 * np.sqrt(Af.shape[0]))
    out = []
    for tr, te in ((fold, ~fold), (~fold, fold)):
        A = X[tr].reshape(-1, X.shape[2])
        cn = np.linalg.norm(A, axis=0)
        cn[cn == 0] = 1.0
        if np.linalg.matrix_rank(A / cn, tol=1e-8 * np.sqrt(A.shape[0])) < rank_full:
            # a designed experiment (rate table: one axis and one sense of rotation at a time)
            # can leave a fold without the excitation a column needs: no out-of-sample verdict
            return float("nan")
        th, *_ = np.linalg.lstsq(A / cn, y[tr].reshape(-1), rcond=1e-10)
        out.append(y[te] - np.einsum("mip,p->mi", X[te], th / cn))
    return _rms(np.concatenate(out))


def _cv_min(res: Residual) -> int:
    # a few known-angle windows among many still ones cannot be split into folds
    return res.m + 1 if res.kind == "angles" else 40


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.asarray(x, float) ** 2)))


def attitude_error_deg(res: Residual, rec: Recording, correction_rad_s: np.ndarray) -> float:
    """RMS attitude error of the corrected gyro against the reference, deg (NaN if undefined).

    ``rate``: integrate from the reference's first attitude (``ref_q*`` or the integrated
    reference rate) and compare over the recording. ``attitude``: same against ``ref_q*``
    where valid. ``still``: the integrated angle from each still window's start. ``angles``:
    RMS over the known-rotation segments of |∫ω dt − φ|.
    """
    t = rec.t_s
    w = rec.gyro_rad_s - correction_rad_s
    if res.kind == "angles":
        T = res.duration_s
        # y_after·T = ∫(ω − c)dt − φ
        d = (res.y_rad_s - res.window_mean(correction_rad_s)) * T[:, None]
        rot = res.is_rotation if res.is_rotation is not None else np.ones(res.m, bool)
        d = d[rot]
        if res.angle_mode == "axis" and res.angle_S_rad is not None:
            phi = res.angle_S_rad[rot]
            u = phi / np.maximum(np.linalg.norm(phi, axis=1, keepdims=True), 1e-300)
            d = np.sum(d * u, axis=1, keepdims=True)  # only the along-axis angle is known
        return float(np.degrees(np.sqrt(np.mean(np.sum(d**2, axis=1)))))
    if res.kind == "still":
        # windows are contiguous blocks: the angle accumulates inside each still run
        return _still_runs_error(res, integrate_gyro(t, w, hold="backward"))
    if res.kind == "rate":
        q_ref = rec.ref_quat_wxyz
        if q_ref is None or not np.all(np.isfinite(q_ref)):
            ref = rec.ref_rate_rad_s
            if ref is None or not np.all(np.isfinite(ref)):
                return float("nan")
            q_ref = integrate_gyro(t, ref, hold="backward")
        q = integrate_gyro(t, w, q0_wxyz=q_ref[0], hold="backward")
        return float(np.degrees(_rms(error_angle_rad(q, q_ref))))
    # attitude
    q_ref = rec.ref_quat_wxyz
    ok = np.all(np.isfinite(q_ref), axis=1)
    i0 = int(np.flatnonzero(ok)[0])
    q = integrate_gyro(t[i0:], w[i0:], q0_wxyz=q_ref[i0], hold="backward")
    e = error_angle_rad(q[ok[i0:]], q_ref[i0:][ok[i0:]])
    return float(np.degrees(_rms(e)))


def _still_runs_error(res: Residual, q: np.ndarray) -> float:
    """RMS over still windows of the angle integrated since the start of their still run."""
    a, b = res.win_start, res.win_stop
    run_start = a.copy()
    for k in range(1, a.size):
        run_start[k] = run_start[k - 1] if a[k] == b[k - 1] else a[k]
    e = error_angle_rad(q[b], q[run_start])
    return float(np.degrees(_rms(e)))


def _remaining(res: Residual, e: np.ndarray) -> Remaining:
    T = res.duration_s
    win = float(np.median(T))
    lb = lsq.ljung_box_p(e)
    # spectrum and Allan deviation on the longest run of evenly spaced windows (still
    # segments, dropped windows and known-rotation windows break the spacing)
    even = np.concatenate([[False], (np.abs(np.diff(res.t_mid_s) - win) <= 0.05 * win)
                           & (np.abs(T[1:] - win) <= 0.05 * win)])
    best, cur, start, best_start = 0, 0, 0, 0
    for k in range(res.m):
        if k > 0 and even[k]:
            cur += 1
        else:
            cur, start = 1, k
        if cur > best:
            best, best_start = cur, start
    uniform = best > 16
    if uniform:
        e = e[best_start:best_start + best]
        fs = 1.0 / win
        f, P = signal.welch(e, fs=fs, axis=0, nperseg=min(256, e.shape[0]))
        from .allan import octave_m, oadev

        m = octave_m(e.shape[0])
        m = m[m <= e.shape[0] // 3] if (m <= e.shape[0] // 3).any() else m[:1]
        taus, adev = None, []
        for i in range(3):
            taus, d, _ = oadev(e[:, i], fs, m)
            adev.append(d)
        adev = np.stack(adev, axis=1)
        ok = np.all(adev > 0, axis=1)
        slope = (np.polyfit(np.log(taus[ok]), np.log(adev[ok]), 1)[0]
                 if ok.sum() >= 2 else np.full(3, np.nan))
    else:
        f, P = np.zeros(0), np.zeros((0, 3))
        taus, adev, slope = np.zeros(0), np.zeros((0, 3)), np.full(3, np.nan)
    return Remaining(ljung_box_p=float(lb), window_s=win, welch_freq_hz=f, welch_psd=P,
                     allan_tau_s=np.asarray(taus), allan_adev_rad_s=adev, allan_slope=np.asarray(slope))


def _test(model: _Model, current: Sequence[str], cand: str, threshold: float, rms_before: float,
          e_current: np.ndarray | None = None, cv_base: float | None = None):
    """Fit current + cand and Wald-test cand's observable parameters.

    ``e_current`` is the current model's window residual (M, 3) and ``cv_base`` its
    out-of-sample RMS (:func:`_cv_rms`), for the out-of-sample check.
    Returns (Evidence, fit).
    """
    added = _with_companion(current, cand)
    fit, e = model.fit(list(current) + added)
    # the test is on the candidate's own columns; a companion (constant term) is part of the
    # base model of the test, so a thermal candidate must add something beyond a constant
    cols = list(range(fit.slices[cand].start, fit.slices[cand].stop))
    idx = [p for p in cols if np.isfinite(fit.stderr[p])]
    names = [fit.names[p].split(".", 1)[1] for p in cols]
    unobs = tuple(n for n, p in zip(names, cols) if p not in idx)
    q = len(idx)
    df2 = max(model.res.m - fit.rank, 1)
    if q:
        th = fit.theta[idx]
        C = fit.cov[np.ix_(idx, idx)]
        try:
            W = float(th @ np.linalg.solve(C, th))
        except np.linalg.LinAlgError:
            W = float(th @ np.linalg.pinv(C) @ th)
        F = W / q
        p = float(stats.f.sf(F, q, df2))
        lp = float(stats.f.logsf(F, q, df2) / np.log(10))
        if not np.isfinite(lp):  # underflow: asymptotic χ²_q tail
            lp = _log10_chi2_sf(W, q)
    else:
        F, p, lp = 0.0, 1.0, 0.0
    rms_after = _rms(e)
    # out of sample: the model plus the candidate, refitted on one fold, must predict the
    # other better than the model alone; where a fold cannot identify the joint model (a rate
    # table turning one axis and one sense at a time), the candidate's own columns fitted to
    # the current residual must
    cv_red = float("nan")
    if e_current is not None:
        mw = _cv_min(model.res)
        if cv_base is not None and np.isfinite(cv_base):
            cv_full = _cv_rms(model.res.y_rad_s, model.design(list(current) + added)[0], min_windows=mw)
            if np.isfinite(cv_full):
                cv_red = 1.0 - cv_full / max(cv_base, 1e-300)
        if not np.isfinite(cv_red):
            Xc, _, _ = model.design(added)
            cv_red = 1.0 - _cv_rms(e_current, Xc, min_windows=mw) / max(_rms(e_current), 1e-300)
    ev = Evidence(
        statistic=F, df1=q, df2=df2, p_value=p, log10_p=lp, threshold=threshold,
        params={n: float(fit.theta[p_]) for n, p_ in zip(names, cols)},
        std_errors={n: float(fit.stderr[p_]) for n, p_ in zip(names, cols)},
        unobservable=unobs,
        rms_reduction=1.0 - rms_after / rms_before if rms_before > 0 else 0.0,
        cv_rms_reduction=cv_red,
        attitude_reduction=float("nan"),
        hac_bandwidth=float(fit.hac_bandwidth),
    )
    return ev, fit


def _log10_chi2_sf(W: float, q: int) -> float:
    """log10 P(χ²_q > W) for large W: −W/2 + (q/2 − 1)·ln(W/2) − lnΓ(q/2) (+ O(1/W))."""
    from scipy.special import gammaln

    lp = float(stats.chi2.logsf(W, q))
    if not np.isfinite(lp):
        lp = -W / 2 + (q / 2 - 1) * np.log(W / 2) - float(gammaln(q / 2))
    return lp / np.log(10)


_MIN_ATTITUDE_DEG = 1e-3
_TAU_ITERATIONS = 4
_TAU_TOL_S = 1e-6


def _advance(rec: Recording, tau_s: float) -> Recording:
    """The recording with the gyro advanced by τ: gyro'(t) = gyro(t + τ) (cubic spline, ends
    held), which undoes a lag τ of the gyro behind the reference exactly (no linearisation)."""
    from dataclasses import replace

    from scipy.interpolate import CubicSpline

    t = rec.t_s
    tq = np.clip(t + tau_s, t[0], t[-1])
    g = CubicSpline(t, rec.gyro_rad_s, axis=0)(tq)
    return replace(rec, gyro_rad_s=g)


def _with_companion(current: Sequence[str], cand: str) -> list[str]:
    comp = COMPANION.get(cand)
    return [comp, cand] if comp is not None and comp not in current else [cand]


def _params_table(fit, effects) -> dict:
    out = {}
    if fit is None:
        return out
    for e in effects:
        sl = fit.slices[e]
        out[e] = {fit.names[p].split(".", 1)[1]: [float(fit.theta[p]), float(fit.stderr[p])]
                  for p in range(sl.start, sl.stop)}
        if e == "earth_rate":
            om = fit.theta[sl]
            mag = float(np.linalg.norm(om))
            out[e]["magnitude_rad_s"] = [mag, float("nan")]
            if mag > 0:
                out[e]["latitude_rad_if_W_is_up"] = [float(np.arcsin(np.clip(om[2] / mag, -1, 1))), float("nan")]
    return out


#: Still references: g-sensitivity needs poses whose specific force differs by at least this
#: much (m/s², ≈ 0.2 g) on some axis; within one pose, changes of f mean motion, not a signal.
_MIN_POSE_CHANGE_M_S2 = 2.0


def _n_poses(f: np.ndarray, tol_m_s2: float = _MIN_POSE_CHANGE_M_S2) -> int:
    """Number of distinct static poses among window-mean specific forces f (M, 3): greedy
    clustering, a new pose when f is farther than ``tol_m_s2`` from every known pose."""
    centres: list[np.ndarray] = []
    for v in f:
        if all(np.linalg.norm(v - c) > tol_m_s2 for c in centres):
            centres.append(v)
    return len(centres)


def _input_check(res: Residual, effect: str) -> str | None:
    """Reason why a candidate cannot be tested on these data, or None."""
    inp = res.inputs
    needs = {
        "bias_thermal": "temp", "bias_temp_rate": "temp", "scale_thermal": "temp",
        "g_sensitivity": "accel", "g2_sensitivity": "accel",
    }.get(effect)
    if needs == "temp" and inp.temp_c is None:
        return "no temp_c column"
    if needs == "accel" and inp.f_S_m_s2 is None:
        return "no accel columns"
    if needs == "accel" and res.kind in ("still", "angles"):
        f = res.window_mean(np.nan_to_num(np.asarray(inp.f_S_m_s2, float)))
        rot = res.is_rotation if res.is_rotation is not None else np.zeros(res.m, bool)
        fs = f[~rot]
        poses = _n_poses(fs)
        if poses < 2:
            return ("one static pose: the specific force hardly changes, so g-sensitivity is a bias here "
                    "(and small changes of f mean the sensor moved)")
        if poses < 3:
            return ("two static poses: a bias change between them (drift, warm-up) explains the same step; "
                    "g-sensitivity needs three or more poses")
    if effect == "earth_rate" and res.R_WS is None:
        return "no attitude to resolve the Earth rate (it is a bias in a fixed pose)"
    if effect == "time_offset" and res.kind == "angles":
        return "known angles carry no timing: a lag between gyro and reference needs a time-resolved reference"
    if effect in ("scale", "scale_thermal", "scale_asymmetry", "scale_nonlinearity", "misalignment",
                  "time_offset") and res.kind == "still":
        return "still data: the true rate is zero, rate-proportional errors are invisible"
    return None


# ---------------------------------------------------------------------------- public
def loop_residual(
    res: Residual,
    rec: Recording,
    *,
    declared: Sequence[str],
    candidates: Sequence[str] | None = None,
    alpha: float = 0.01,
    thermal_order: int = 1,
    min_rms_reduction: float = 0.005,
    min_attitude_reduction: float = 0.05,
    max_steps: int = 8,
    rebuild=None,
) -> LoopResult:
    """Run the loop on a prepared :class:`~gyrocore.residual.Residual` (see :func:`run_loop`).

    ``rebuild(recording) -> Residual`` (optional) rebuilds the residual from a recording; it
    enables the Gauss–Newton refinement of ``time_offset`` (see :func:`run_loop`).
    """
    declared = E.check_effect_names(declared)
    notes = list(res.notes)
    ignored = [d for d in declared if d not in FITTABLE]
    if ignored:
        notes.append(f"declared effects without linear regressors are not fitted: {', '.join(ignored)}")
    model_effects = [d for d in declared if d in FITTABLE]
    if candidates is None:
        cand_all = [c for c in CANDIDATES if c not in declared]
    else:
        cand_all = [c for c in E.check_effect_names(candidates) if c not in declared]
        bad = [c for c in cand_all if c not in CANDIDATES]
        if bad:
            raise GyroInputError(f"the loop cannot trace {', '.join(bad)} (no linear regressors)")
    orders = {"bias_thermal": thermal_order, "scale_thermal": thermal_order}
    model = _Model(res, orders)
    untestable: dict[str, str] = {}
    for c in list(cand_all) + list(model_effects):
        why = _input_check(res, c)
        if why is None:
            try:
                model.block(c)
            except GyroInputError as exc:
                why = str(exc)
        if why is not None:
            if c in model_effects:
                raise GyroInputError(f"declared effect {c} cannot be fitted here: {why}")
            untestable[c] = why
    cands = [c for c in cand_all if c not in untestable]

    rec0 = rec
    tau_acc = 0.0

    def refit(res, model, rec, tau_acc):
        """Joint fit; with time_offset in the model, re-linearise around its estimate."""
        fit, e = model.fit(model_effects)
        if rebuild is None or "time_offset" not in model_effects or res.kind not in ("rate", "attitude"):
            return res, model, rec, tau_acc, fit, e
        for _ in range(_TAU_ITERATIONS):
            d = float(fit.effect_theta("time_offset")[0])
            if not np.isfinite(d) or abs(d) < _TAU_TOL_S:
                break
            tau_acc += d
            rec = _advance(rec0, tau_acc)
            res = rebuild(rec)
            model = _Model(res, orders)
            fit, e = model.fit(model_effects)
        return res, model, rec, tau_acc, fit, e

    res, model, rec, tau_acc, fit, e = refit(res, model, rec, tau_acc)
    history = [e]
    rms0 = _rms(e)
    att0 = attitude_error_deg(res, rec, model.correction(fit, model_effects))
    rms_cur, att_cur = rms0, att0
    steps: list[Step] = []
    last_tests: dict[str, Evidence] = {}
    for _ in range(max_steps):
        remaining = [c for c in cands if c not in model_effects]
        if not remaining:
            break
        cv_base = _cv_rms(res.y_rad_s, model.design(model_effects)[0], min_windows=_cv_min(res))
        trial = {c: _test(model, model_effects, c, 0.0, rms_cur, e, cv_base) for c in remaining}
        testable = [c for c in remaining if trial[c][0].df1 > 0]
        for c in remaining:
            if c not in testable:
                untestable[c] = "not observable given the model: " + ", ".join(trial[c][0].unobservable)
        if not testable:
            break
        thr = alpha / len(testable)
        evs: dict[str, Evidence] = {}
        for c in testable:
            ev, f = trial[c]
            att_red = float("nan")
            if ev.p_value < thr:
                att = attitude_error_deg(res, rec, model.correction(f, model_effects + _with_companion(model_effects, c)))
                # relative change, defined only above 1 mdeg (below, the reference is already
                # matched to numerical precision, e.g. three known angles and three scales)
                att_red = 1.0 - att / att_cur if att_cur > _MIN_ATTITUDE_DEG else float("nan")
            evs[c] = Evidence(**{**ev.__dict__, "threshold": thr, "attitude_reduction": att_red})
        def practical(ev: Evidence) -> bool:
            # out of sample (2-fold blocked): an effect fitted to coloured noise does not
            # predict the other folds; and of a size that matters, in the residual or in the
            # attitude
            size = ev.rms_reduction >= min_rms_reduction or (
                np.isfinite(ev.attitude_reduction) and ev.attitude_reduction >= min_attitude_reduction)
            held = ev.cv_rms_reduction > 0 or not np.isfinite(ev.cv_rms_reduction)
            if res.kind == "angles" and np.isfinite(ev.attitude_reduction):
                # the known angles are the reference: an effect that makes them worse by more
                # than a quarter of their uncertainty is refuted
                worse_deg = -ev.attitude_reduction * att_cur
                held = held and worse_deg <= 0.25 * np.degrees(res.angle_sigma_rad)
            return held and size
        sig = [c for c in testable if evs[c].p_value < thr and practical(evs[c])]
        last_tests = evs
        if not sig:
            break
        sig.sort(key=lambda c: (evs[c].log10_p, -evs[c].statistic))
        best = sig[0]
        ambiguous, nested = [], []
        for r in sig[1:]:
            ev_b, _ = _test(model, model_effects + _with_companion(model_effects, r), best, thr, rms_cur)
            ev_r, _ = _test(model, model_effects + _with_companion(model_effects, best), r, thr, rms_cur)
            if ev_r.df1 == 0 and ev_b.df1 > 0 and not ev_b.significant:
                nested.append(r)  # r is contained in best and best adds nothing to it
            elif not ev_b.significant and not ev_r.significant:
                ambiguous.append(r)
        if nested:  # parsimony: the smaller effect that explains the same residual
            best = min(nested, key=lambda c: (evs[c].log10_p, -evs[c].statistic))
            ambiguous = [c for c in ambiguous if c != best]
        if ambiguous:
            # evidence decides when it differs by ≥ 1 decade of p; otherwise (a tie the data
            # cannot break) the simpler effect: fewer parameters, then the lower-order, more
            # common one (earlier in CANDIDATES)
            pool = [best] + ambiguous
            close = [c for c in pool if evs[c].log10_p <= evs[best].log10_p + 1.0]
            pick = min(close, key=lambda c: (evs[c].df1, CANDIDATES.index(c)))
            ambiguous = [c for c in pool if c != pick]
            best = pick
        # `best` has the strongest evidence (smallest p-value, which accounts for its number
        # of parameters); the ambiguous ones are reported with it.
        model_effects.extend(_with_companion(model_effects, best))
        res, model, rec, tau_acc, fit, e = refit(res, model, rec, tau_acc)
        history.append(e)
        rms_new = _rms(e)
        att_new = attitude_error_deg(res, rec, model.correction(fit, model_effects))
        evb = evs[best]
        steps.append(Step(
            effect=best,
            evidence=Evidence(**{**evb.__dict__, "ambiguous_with": tuple(ambiguous)}),
            residual_rms_before_rad_s=rms_cur, residual_rms_after_rad_s=rms_new,
            attitude_error_before_deg=att_cur, attitude_error_after_deg=att_new,
        ))
        last_tests = {}
        rms_cur, att_cur = rms_new, att_new
    found = [s.effect for s in steps]
    params = _params_table(fit, model_effects)
    if tau_acc != 0.0 and "time_offset" in params:
        v, se = params["time_offset"]["tau_s"]
        params["time_offset"]["tau_s"] = [tau_acc + v, se]
        notes.append(f"time_offset re-linearised (Gauss-Newton): the gyro was advanced by {tau_acc:.6g} s and "
                     "the fit repeated; tau_s is the total")
    return LoopResult(
        declared=tuple(declared),
        found=tuple(steps),
        reference=res.kind,
        description=res.description,
        residual_rms_before_rad_s=rms0,
        residual_rms_after_rad_s=rms_cur,
        attitude_error_before_deg=att0,
        attitude_error_after_deg=att_cur,
        params=params,
        tested={c: ev for c, ev in last_tests.items() if c not in found},
        untestable=untestable,
        remaining=_remaining(res, e),
        notes=tuple(notes),
        n_windows=res.m,
        alpha=alpha,
        residual=res,
        history=tuple(history),
    )


def run_loop(
    rec: Recording,
    *,
    declared: Sequence[str],
    segments: Sequence[Segment] | None = None,
    candidates: Sequence[str] | None = None,
    reference: str = "auto",
    window_s: float | None = None,
    alpha: float = 0.01,
    thermal_order: int = 1,
    min_rms_reduction: float = 0.005,
    min_attitude_reduction: float = 0.05,
    max_steps: int = 8,
    angle_sigma_deg: float = 2.0,
    axis_sigma_deg: float = 5.0,
    angle_mode: str = "rotation",
) -> LoopResult:
    """Close the loop on one recording.

    Parameters
    ----------
    rec : Recording
        Measured or simulated data with some reference (``ref_*_rad_s``, ``ref_q*``) or
        ``segments``.
    declared : sequence of str
        Effects already in the model (fitted jointly from the start).
    segments : sequence of Segment, optional
        Still / known-rotation segments (see :mod:`gyrocore.residual`).
    candidates : sequence of str, optional
        Effects to trace (default: every :data:`CANDIDATES` entry not declared).
    reference : {"auto", "rate", "attitude", "still", "angles"}
    window_s : float, optional
        Observation window length, s (default: see :func:`gyrocore.residual.build_residual`).
    alpha : float
        Family-wise error rate over all candidates and steps (Holm).
    thermal_order : int
        Polynomial order of the thermal candidates.
    min_rms_reduction, min_attitude_reduction : float
        Practical significance: a winner must cut the window residual RMS or the attitude
        error by at least these fractions, and must predict the other half of the recording
        (see the module docstring).
    max_steps : int
        At most this many effects are added.
    angle_sigma_deg, axis_sigma_deg : float
        Uncertainty of each known rotation angle and of its axis (``"angles"`` reference),
        degrees.
    angle_mode : {"rotation", "axis"}
        Known rotations: whole rotations (start/end poses known) or the total angle about the
        axis only (free hand turns); see :func:`gyrocore.residual.build_residual`.

    Returns
    -------
    LoopResult
    """
    if not 0 < alpha < 1:
        raise GyroInputError(f"alpha must be in (0, 1), not {alpha}")
    with _single_thread():
        res = build_residual(rec, reference=reference, segments=segments, window_s=window_s,
                             angle_sigma_deg=angle_sigma_deg, axis_sigma_deg=axis_sigma_deg,
                             angle_mode=angle_mode)
        def rebuild(r: Recording) -> Residual:
            return build_residual(r, reference=res.kind, segments=segments, window_s=window_s,
                                  angle_sigma_deg=angle_sigma_deg, axis_sigma_deg=axis_sigma_deg,
                             angle_mode=angle_mode)

        return loop_residual(
            res, rec, declared=declared, candidates=candidates, alpha=alpha, thermal_order=thermal_order, rebuild=rebuild,
            min_rms_reduction=min_rms_reduction, min_attitude_reduction=min_attitude_reduction,
            max_steps=max_steps,
        )


# ---------------------------------------------------------------------------- plots
_NATURAL = {
    "bias_ramp": ("time since start, s", lambda r: np.repeat(r.t_mid_s[:, None] - r.inputs.t_s[0], 3, axis=1)),
    "bias_thermal": ("temperature, °C", lambda r: np.repeat(r.window_mean(
        np.repeat(np.asarray(r.inputs.temp_c, float)[:, None], 3, axis=1))[:, :1], 3, axis=1)),
    "bias_temp_rate": ("dT/dt, °C/s", lambda r: np.repeat(r.window_mean(
        np.repeat(r.inputs.temp_rate_c_s()[:, None], 3, axis=1))[:, :1], 3, axis=1)),
    "scale": ("reference rate, rad/s", lambda r: r.window_mean(np.asarray(r.inputs.omega_S_rad_s, float))),
    "scale_asymmetry": ("reference rate, rad/s", lambda r: r.window_mean(np.asarray(r.inputs.omega_S_rad_s, float))),
    "scale_nonlinearity": ("reference rate, rad/s", lambda r: r.window_mean(np.asarray(r.inputs.omega_S_rad_s, float))),
    "time_offset": ("rate derivative dω/dt, rad/s²", lambda r: r.window_mean(
        np.gradient(np.asarray(r.inputs.omega_S_rad_s, float), np.asarray(r.inputs.t_s, float), axis=0))),
}


def plot_found(result: LoopResult, out_dir, *, max_points: int = 4000, prefix: str = "loop") -> list:
    """Residual against the found effect's regressor, before and after each step (PNG per step).

    The x axis is the effect's physical variable where it has one per axis (time, T, dT/dt,
    rate, rate derivative) and otherwise the effect's fitted contribution X·θ (a partial
    residual plot: before the step the residual follows the 1:1 line, after it is flat).

    Returns the list of written paths.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from pathlib import Path

    from .recording import atomic_write_bytes
    import io

    out = Path(out_dir)
    res = result.residual
    paths = []
    if res is None:
        return paths
    D = 180.0 / np.pi
    rng = np.random.default_rng(0)  # subsampling of points only
    idx = np.arange(res.m) if res.m <= max_points else np.sort(rng.choice(res.m, max_points, replace=False))
    for k, step in enumerate(result.found):
        before, after = result.history[k], result.history[k + 1]
        eff = step.effect
        if before.shape != after.shape or before.shape[0] != res.m:
            continue  # the windows changed (re-linearised time offset dropped a glitch window)
        if eff in _NATURAL:
            xlabel, fx = _NATURAL[eff]
            x = fx(res)
        else:
            names, X = res.regressors(eff, order=1) if eff not in ("bias_thermal", "scale_thermal") else (None, None)
            th = np.array([step.evidence.params[n] for n in step.evidence.params if not n.startswith("bias.")
                           and not n.startswith("scale.")])
            if X is not None and X.shape[2] == th.size:
                x = np.einsum("mip,p->mi", X, th) * D
                xlabel = f"fitted {eff} contribution X·θ, deg/s"
            else:
                x = np.repeat(res.t_mid_s[:, None], 3, axis=1)
                xlabel = "time, s"
        fig, axes = plt.subplots(1, 3, figsize=(12, 3.6), sharey=True)
        for i, ax in enumerate(axes):
            ax.plot(x[idx, i], before[idx, i] * D, ".", ms=2, alpha=0.5, label="before")
            ax.plot(x[idx, i], after[idx, i] * D, ".", ms=2, alpha=0.5, label="after")
            ax.set_title(f"axis {'xyz'[i]}")
            ax.set_xlabel(xlabel)
            ax.grid(True, alpha=0.3)
        axes[0].set_ylabel(f"window residual, deg/s ({res.kind})")
        axes[0].legend(loc="best", markerscale=4)
        ev = step.evidence
        fig.suptitle(f"step {k + 1}: {eff} (F = {ev.statistic:.3g}, log10 p = {ev.log10_p:.3g}); "
                     f"RMS {step.residual_rms_before_rad_s * D:.3g} -> {step.residual_rms_after_rad_s * D:.3g} deg/s")
        fig.tight_layout()
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=90)
        plt.close(fig)
        p = out / f"{prefix}_step{k + 1}_{eff}.png"
        atomic_write_bytes(p, buf.getvalue())
        paths.append(p)
    return paths
