"""The residual loop: find what the model still leaves, name the effect, add it, refit.

Start from the declared effects, fit them jointly to the residual of
:mod:`gyrocore.loop.residual` (whatever reference the data offer), then repeat:

1. **Trace.** For every catalogue effect not yet in the model (each through its physical
   regressors from :func:`gyrocore.effects.registry.design`, integrated over the observation windows),
   refit the model plus that candidate jointly (:func:`gyrocore.calib.lsq.solve`) and test
   "candidate parameters = 0" with a Wald statistic on a **HAC** covariance — ``lsq``'s
   ``"hac"``: the sandwich with each axis' residual autocovariance (short-lag sample values
   plus a fitted Gauss–Markov tail), so that coloured residuals (on-chip low-pass, bias
   instability, rate random walk, an optical reference's noise) do not pass for a signal —
   referred to F(q, M − P) (q candidate parameters, M windows, P fitted parameters) — and,
   as a second test that must reject too, with the covariance implied by a white + random-walk
   noise model identified on the residual's Allan variance (:func:`_model_wald`): the HAC's
   slow component is added only when significant, and slowly varying regressors (time, a
   warm-up temperature) then pass Gauss–Markov / random-walk wander for a signal. With a
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
   columns, fitted to the current residual, must predict it instead. It must also predict
   across the two contiguous halves (fitted on one, scored on the other; no verdict where a
   half cannot identify it). This guards against HAC's optimism on short, strongly coloured
   residuals: a ramp fitted to one stretch of wander does not predict the next.
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

from gyrocore.effects import registry as E
from gyrocore.calib import lsq
from gyrocore.attitude import error_angle_rad, integrate_gyro, rate_error_vs_attitude
from gyrocore.errors import GyroInputError
from gyrocore.data.recording import Recording
from . import search as S
from .residual import Residual, Segment, build_residual
from .search import Unexplained, column_axis
from gyrocore.calib.stream import Rows, SpilledRecording, held_correction, rows_of

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
    hac_log10_p, model_log10_p : float
        log10 p of the two Wald tests the candidate must pass (:func:`_model_wald`): on the
        HAC covariance (F reference) and on the covariance implied by a white + random-walk +
        Gauss–Markov noise model identified on the residual (χ² reference). ``p_value`` /
        ``log10_p`` are the larger of the two (both must reject); NaN where the model-based
        test does not apply (known-angle references, fewer than 64 windows).
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
    hac_log10_p: float = float("nan")
    model_log10_p: float = float("nan")

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
            "welch_peak_hz": [
                float(self.welch_freq_hz[1:][np.argmax(self.welch_psd[1:, i])]) if self.welch_freq_hz.size > 2 else None
                for i in range(3)
            ],
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
        Window residual with the declared model, then after each catalogue step, rad/s.
    unexplained : tuple of gyrocore.loop.search.Unexplained
        Effects outside the catalogue described by the open search (DESIGN.md
        "Effects outside the catalogue"), in the order they were added.
    open_search : dict
        What the open search tested last (the strongest candidate of each kind, not taken),
        or why it did not run.
    t0_c : float or None
        Reference temperature of the thermal polynomials (mean temperature), °C.
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
    unexplained: tuple = ()
    open_search: dict = field(default_factory=dict)
    t0_c: float | None = None

    @property
    def found_effects(self) -> list[str]:
        return [s.effect for s in self.found]

    def to_json(self) -> dict:
        """The DESIGN.md JSON (plus extra keys)."""

        def ev(e: Evidence) -> dict:
            return {
                "statistic": e.statistic,
                "df1": e.df1,
                "df2": e.df2,
                "p_value": e.p_value,
                "log10_p": e.log10_p,
                "threshold": e.threshold,
                "params": e.params,
                "std_errors": e.std_errors,
                "unobservable": list(e.unobservable),
                "rms_reduction": e.rms_reduction,
                "attitude_reduction": e.attitude_reduction,
                "hac_bandwidth_windows": e.hac_bandwidth,
                "ambiguous_with": list(e.ambiguous_with),
                "cv_rms_reduction": e.cv_rms_reduction,
                "hac_log10_p": e.hac_log10_p,
                "model_log10_p": e.model_log10_p,
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
            "unexplained": [u.to_json() for u in self.unexplained],
            "open_search": self.open_search,
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
        base, axis = split_axis(effect)
        names, X = self.res.regressors(base, order=self.orders.get(base, 1))
        if axis is None:
            return names, X
        cols = [p for p, n in enumerate(names) if column_axis(n) == axis]
        return [names[p] for p in cols], X[:, :, cols]

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
                f = lsq.solve(
                    y,
                    X,
                    names,
                    slices,
                    weights=self.angle_weights(),
                    covariance="ols",
                    axis_weighting=False,
                    on_unobservable="drop",
                    min_excitation_snr=0.0,
                )
            else:
                f = lsq.solve(y, X, names, slices, covariance="hac", on_unobservable="drop", min_excitation_snr=0.0)
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
        terms = []
        for e in effects if fit is not None else ():
            base, axis = split_axis(e)
            th = fit.effect_theta(e)
            if axis is not None:  # one axis of a family term: the other columns are 0
                names = self.res.regressors(base, order=1)[0]
                full = np.zeros(len(names))
                full[[p for p, n in enumerate(names) if column_axis(n) == axis]] = th
                th = full
            terms.append((base, th, self.orders.get(base, 1)))
        if self.res.lazy:
            # a recording on disk: the correction is computed a window at a time where it is used
            return self.res.correction_rows(terms)
        c = np.zeros((self.res.inputs.n, 3))
        for base, th, order in terms:
            c += self.res.sample_correction(base, th, order=order)
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
    if isinstance(rec, SpilledRecording):
        return _attitude_error_spilled(res, rec, correction_rad_s)
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


def _attitude_error_spilled(res: Residual, rec: SpilledRecording, correction) -> float:
    """:func:`attitude_error_deg` (``rate`` reference) of a recording on disk: the corrected
    gyro integrated a window at a time, the attitude carried across windows (each window
    starts from the previous one's last attitude and sample: the backward-hold step across the
    cut is taken once), the squared error angles summed."""
    if res.kind != "rate":  # pragma: no cover - _build_spilled makes only rate residuals
        raise GyroInputError("a recording on disk has only the rate reference")
    q_ref = rec.reference_quaternions()
    if q_ref is None:
        return float("nan")
    t = rec.t_s
    q_carry = w_last = None
    s2, cnt = 0.0, 0
    for lo, hi in rec.chunks():
        w = rec.gyro_rad_s.rows(lo, hi) - rows_of(correction, lo, hi)
        qr = q_ref.rows(lo, hi)
        if q_carry is None:
            q = integrate_gyro(t[lo:hi], w, q0_wxyz=qr[0], hold="backward")
        else:
            q = integrate_gyro(t[lo - 1 : hi], np.vstack([w_last, w]), q0_wxyz=q_carry, hold="backward")[1:]
        e = error_angle_rad(q, qr)
        s2 += float(np.sum(e * e))
        cnt += e.size
        q_carry, w_last = q[-1], w[-1:]
    return float(np.degrees(np.sqrt(s2 / cnt)))


def _still_runs_error(res: Residual, q: np.ndarray) -> float:
    """RMS over still windows of the angle integrated since the start of their still run."""
    a, b = res.win_start, res.win_stop
    run_start = a.copy()
    for k in range(1, a.size):
        run_start[k] = run_start[k - 1] if a[k] == b[k - 1] else a[k]
    e = error_angle_rad(q[b], q[run_start])
    return float(np.degrees(_rms(e)))


def _remaining(res: Residual, e: np.ndarray) -> Remaining:
    win = float(np.median(res.duration_s))
    lb = lsq.ljung_box_p(e)
    # spectrum and Allan deviation on the longest run of evenly spaced windows (still
    # segments, dropped windows and known-rotation windows break the spacing)
    e_run, _, fs, _ = _window_line_series(res, e)
    if e_run.shape[0] > 16:
        e = e_run
        f, P = signal.welch(e, fs=fs, axis=0, nperseg=min(256, e.shape[0]))
        from gyrocore.noise.allan import octave_m, oadev

        m = octave_m(e.shape[0])
        m = m[m <= e.shape[0] // 3] if (m <= e.shape[0] // 3).any() else m[:1]
        taus, adev = None, []
        for i in range(3):
            taus, d, _ = oadev(e[:, i], fs, m)
            adev.append(d)
        adev = np.stack(adev, axis=1)
        ok = np.all(adev > 0, axis=1)
        slope = np.polyfit(np.log(taus[ok]), np.log(adev[ok]), 1)[0] if ok.sum() >= 2 else np.full(3, np.nan)
    else:
        f, P = np.zeros(0), np.zeros((0, 3))
        taus, adev, slope = np.zeros(0), np.zeros((0, 3)), np.full(3, np.nan)
    return Remaining(
        ljung_box_p=float(lb),
        window_s=win,
        welch_freq_hz=f,
        welch_psd=P,
        allan_tau_s=np.asarray(taus),
        allan_adev_rad_s=adev,
        allan_slope=np.asarray(slope),
    )


def _test(
    model: _Model,
    current: Sequence[str],
    cand: str,
    threshold: float,
    rms_before: float,
    e_current: np.ndarray | None = None,
    cv_base: float | None = None,
):
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
    names = [fit.names[p].rsplit(".", 1)[1] for p in cols]
    unobs = tuple(n for n, p in zip(names, cols) if p not in idx)
    q = len(idx)
    df2 = model.res.m - fit.rank
    resid_dof = 3 * model.res.m - fit.rank  # window residuals (3 axes each) left after the fit
    if q and resid_dof < 1:
        # the model plus the candidate fits every window residual exactly (3 hand turns, bias
        # declared: 9 residuals, 3 + 6 misalignment parameters): no residual is left to judge
        # the fit by, so the candidate is not testable (a floor of 1 used to turn the exact fit
        # into F ~ 1e26 and a 'found' misalignment of 6 rad)
        unobs = (
            f"no residual degrees of freedom left ({3 * model.res.m} window residuals, {fit.rank} parameters with it)",
        )
        idx, q = [], 0
    df2 = max(df2, 1)
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
    lp_hac = lp
    lp_mod = float("nan")
    if q and model.res.kind != "angles":
        lp_mod = _model_wald(model, fit, list(current) + added, idx)
        if np.isfinite(lp_mod) and lp_mod > lp:
            # both tests must reject: the p-value of the intersection is the larger one
            lp = lp_mod
            p = float(10.0**lp_mod)
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
        if model.res.kind != "angles":
            # and across the two contiguous halves: fitted on one half, the model plus the
            # candidate must predict the other half (extrapolation in time) better than the model
            # alone. An effect of the sensor holds over the whole record; a term fitted to slow
            # wander (Gauss–Markov bias, random walk) does not carry to the next stretch, while
            # the interleaved blocks above interpolate it. NaN (a half cannot identify the
            # columns, e.g. a step or one table axis per half) is no verdict.
            X0 = model.design(list(current))[0]
            b2 = _cv_rms(model.res.y_rad_s, X0, min_windows=mw, n_blocks=2)
            f2 = _cv_rms(model.res.y_rad_s, model.design(list(current) + added)[0], min_windows=mw, n_blocks=2)
            if np.isfinite(b2) and np.isfinite(f2):
                half = 1.0 - f2 / max(b2, 1e-300)
                cv_red = half if not np.isfinite(cv_red) else min(cv_red, half)
            elif _slow_open_term(cand):
                # a slow open term (a library product with t) where a half cannot identify
                # the joint model (a rate table turning one axis per phase): as the interleaved
                # fallback above, the candidate's own columns fitted to the current residual on
                # one half must predict the other. Without it the guard is silent exactly where
                # a t-term can be fitted to wander (mpu6050 turntable null, seed 0:
                # regressor[omega_z*t] on y, docs/loop.md §4c)
                Xc, _, _ = model.design(added)
                h2 = _cv_rms(e_current, Xc, min_windows=mw, n_blocks=2)
                if np.isfinite(h2):
                    half = 1.0 - h2 / max(_rms(e_current), 1e-300)
                    cv_red = half if not np.isfinite(cv_red) else min(cv_red, half)
    ev = Evidence(
        statistic=F,
        df1=q,
        df2=df2,
        p_value=p,
        log10_p=lp,
        threshold=threshold,
        params={n: float(fit.theta[p_]) for n, p_ in zip(names, cols)},
        std_errors={n: float(fit.stderr[p_]) for n, p_ in zip(names, cols)},
        unobservable=unobs,
        rms_reduction=1.0 - rms_after / rms_before if rms_before > 0 else 0.0,
        cv_rms_reduction=cv_red,
        attitude_reduction=float("nan"),
        hac_bandwidth=float(fit.hac_bandwidth),
        hac_log10_p=lp_hac,
        model_log10_p=lp_mod,
    )
    return ev, fit


def _slow_open_term(cand: str) -> bool:
    """True for an open regressor candidate (``regressor[...]@axis``) with a factor ``t``."""
    if not cand.startswith("regressor["):
        return False
    expr = cand[len("regressor[") : cand.rindex("]")]
    try:
        return "t" in S.term_factors(expr)
    except Exception:
        return False


#: Fewest windows for the model-based test (its Allan variance needs octaves up to M/4 ≥ 16).
_MODEL_TEST_MIN_WINDOWS = 64


def _avar_octaves(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Overlapping Allan variance of a window series x (M,) at L = 1, 2, 4, … ≤ M/4 windows.

    Returns (L, AVAR, EDF) with the conservative EDF M/L − 1 (the number of non-overlapping
    adjacent pairs; the overlapping estimate has somewhat more)."""
    M = x.shape[0]
    c = np.concatenate([[0.0], np.cumsum(x)])
    Ls, av, edf = [], [], []
    L = 1
    while L <= M // 4:
        mean = (c[L:] - c[:-L]) / L  # all L-window means
        d = mean[L:] - mean[:-L]  # adjacent, overlapping
        Ls.append(L)
        av.append(0.5 * float(np.mean(d**2)))
        edf.append(max(M / L - 1.0, 1.0))
        L *= 2
    return np.asarray(Ls, float), np.asarray(av), np.asarray(edf)


def _white_rw_noise_model(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """White + random-walk model of a window series: coefficients (σ², q) and their covariance.

    AVAR(L) = σ²/L + q·(2L² + 1)/(6L) (white of variance σ² per window; random walk of
    increment variance q per window), fitted by weighted least squares to the overlapping
    AVAR at octaves up to M/4 with Var(AVAR_j) = 2·AVAR_j²/EDF_j (two passes, the weights
    from the first fit's model values), **not** clipped at zero in the covariance: a random-
    walk part estimated near zero still carries its uncertainty into the test's degrees of
    freedom. The random walk stands for every slow term (flicker, Gauss–Markov, random walk):
    its linear growth of the AVAR beyond the longest octave is exact for a random walk and
    conservative for flicker (flat AVAR) and for Gauss–Markov (saturating AVAR).
    """
    L, av, edf = _avar_octaves(x)
    B = np.column_stack([1.0 / L, (2 * L**2 + 1) / (6 * L)])
    model = np.maximum(av, 1e-300)
    c = np.zeros(2)
    cov = np.full((2, 2), np.inf)
    for _ in range(2):
        w = edf / (2.0 * model**2)
        G = B.T @ (B * w[:, None])
        try:
            cov = np.linalg.inv(G)
        except np.linalg.LinAlgError:
            return np.array([np.var(x), 0.0]), np.full((2, 2), np.inf)
        c = cov @ (B.T @ (w * av))
        c[0] = max(c[0], 0.0)
        model = np.maximum(B @ np.maximum(c, 0.0), 1e-300)
    return c, cov


def _model_wald(model: _Model, fit, effects: Sequence[str], idx: Sequence[int]) -> float:
    """log10 p of the Wald test of columns ``idx`` on a noise-model covariance with its own
    degrees of freedom.

    Why a second test: the HAC covariance of :mod:`gyrocore.calib.lsq` takes the residual's
    autocovariance at short lags plus an exponential tail, and adds a slow component only when
    block means up to M/8 windows show a *significant* excess (α = 1e-3); its F reference has
    M − P denominator degrees of freedom. A slowly varying regressor (``bias_ramp``: t,
    ``bias_thermal``: a warm-up T(t)) has its variance set by the noise at frequencies ≲ 1/T,
    where rate random walk and a Gauss–Markov bias with τc of the record's order put their
    power, and there the data hold only a few degrees of freedom. Measured on 600 synthetic
    nulls (white + flicker + RRW 10 °/h/√h + GM 0.002 °/s, τc 20 s; 40 s, 1333 windows):
    P(p_HAC < 0.001) = 7 % for ``bias_ramp`` and 6 % for ``bias_thermal`` (nominal 0.1 %).

    Here each axis' noise is white + random walk (:func:`_white_rw_noise_model`, identified on
    the alternative's residual so that a real effect is not taken for noise). θ̂ = L·y (L the
    rows of (XᵀWX)⁻¹XᵀW of the tested columns) has covariance V = Σ_axes σ²·L_aL_aᵀ + q·R_aR_aᵀ
    (R the reverse cumulative sums of L: the random walk's min(i, j) covariance) and the
    statistic W = θ̂ᵀV̂⁻¹θ̂ is referred to χ²_q (exact for Gaussian noise of the identified
    model). The two tests fail differently — HAC by leaving out a slow part that is not
    significant at 1e-3, the model by a random-walk level estimated low from a few long-τ
    Allan variances — and a candidate must pass both (the intersection's p-value is the larger
    one). Measured (docs/loop.md §4): on 200 of the nulls above, P(p < 0.001) for ``bias_ramp`` is
    2.5 % for this test alone and 2.5 % for both; with the contiguous-halves guard of
    :func:`_test` the catalogue's family-wise false claims fall from 13 of 300 to 1 of 300 at
    its share α/2 = 0.005. (Referring W to F(q, ν) with Satterthwaite's ν for the uncertainty
    of the random-walk level was measured and dropped: 0 of 600 coloured-noise nulls below p 0.2
    for bias_ramp and no power left for slow effects — a 3× ramp at log10 p −0.5 against −27 for
    HAC: 40 s of data cannot bound a random walk at the record's scale.) Lags are counted in windows (gaps between windows are ignored, as in
    the step test).

    Returns NaN when the test does not apply (fewer than :data:`_MODEL_TEST_MIN_WINDOWS` windows).
    """
    res = model.res
    M = res.m
    if M < _MODEL_TEST_MIN_WINDOWS:
        return float("nan")
    X = model.design(effects)[0]
    kept = [p_ for p_ in range(X.shape[2]) if np.isfinite(fit.stderr[p_])]
    rows = [kept.index(p_) for p_ in idx]
    Xk = X[:, :, kept]
    w = 1.0 / np.asarray(fit.axis_sigma_rad_s, float) ** 2
    G = np.einsum("mip,i,miq->pq", Xk, w, Xk)
    cn = np.sqrt(np.diag(G))
    cn[cn == 0] = 1.0
    Ginv = np.linalg.pinv(G / np.outer(cn, cn)) / np.outer(cn, cn)
    Lr = np.einsum("qp,mip,i->imq", Ginv[rows], Xk, w)  # (3, M, q): θ̂ = Σ_a Lr[a]ᵀ y[:, a]
    e = np.asarray(fit.residual_rad_s, float)
    q_dim = len(rows)
    V = np.zeros((q_dim, q_dim))
    for a in range(3):
        U = Lr[a]
        if not np.any(U):
            continue
        c, _cov = _white_rw_noise_model(e[:, a])
        Vw = U.T @ U
        Rc = np.cumsum(U[::-1], axis=0)[::-1]
        Vr = Rc.T @ Rc
        V += c[0] * Vw + max(c[1], 0.0) * Vr
    V = 0.5 * (V + V.T)
    th = np.asarray(fit.theta, float)[list(idx)]
    try:
        Vinv = np.linalg.inv(V)
    except np.linalg.LinAlgError:
        Vinv = np.linalg.pinv(V)
    W = float(th @ Vinv @ th)
    if not np.isfinite(W) or W < 0:
        return float("nan")
    return _log10_chi2_sf(W, q_dim)


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

    if isinstance(rec, SpilledRecording):  # advanced a window at a time where it is read
        return rec.with_ops(tau_s=tau_s)
    t = rec.t_s
    tq = np.clip(t + tau_s, t[0], t[-1])
    g = CubicSpline(t, rec.gyro_rad_s, axis=0)(tq)
    return replace(rec, gyro_rad_s=g)


def _fittable(effect: str) -> bool:
    """A declared effect the loop fits: a catalogue effect with linear regressors, or a
    registered family term (``periodic[..]``, ``step[..]``, ``regressor[..]``)."""
    if effect in FITTABLE:
        return True
    return "[" in effect and bool(getattr(E.resolve(effect), "fittable", False))


def split_axis(effect: str) -> tuple[str, int | None]:
    """Internal name of one axis of a family term, ``"regressor[omega_x*omega_y]@0"`` ->
    (``"regressor[omega_x*omega_y]"``, 0); other names -> (name, None)."""
    if "@" in effect:
        base, ax = effect.rsplit("@", 1)
        return base, int(ax)
    return effect, None


def _with_companion(current: Sequence[str], cand: str) -> list[str]:
    comp = COMPANION.get(cand)
    return [comp, cand] if comp is not None and comp not in current else [cand]


def _params_table(fit, effects) -> dict:
    out = {}
    if fit is None:
        return out
    for e in effects:
        sl = fit.slices[e]
        base, _ = split_axis(e)
        out.setdefault(base, {}).update(
            {
                fit.names[p].rsplit(".", 1)[1]: [float(fit.theta[p]), float(fit.stderr[p])]
                for p in range(sl.start, sl.stop)
            }
        )
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
        "bias_thermal": "temp",
        "bias_temp_rate": "temp",
        "scale_thermal": "temp",
        "g_sensitivity": "accel",
        "g2_sensitivity": "accel",
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
            return (
                "one static pose: the specific force hardly changes, so g-sensitivity is a bias here "
                "(and small changes of f mean the sensor moved)"
            )
        if poses < 3:
            return (
                "two static poses: a bias change between them (drift, warm-up) explains the same step; "
                "g-sensitivity needs three or more poses"
            )
    if effect == "earth_rate" and res.R_WS is None:
        return "no attitude to resolve the Earth rate (it is a bias in a fixed pose)"
    if effect == "time_offset" and res.kind == "angles":
        return "known angles carry no timing: a lag between gyro and reference needs a time-resolved reference"
    if (
        effect in ("scale", "scale_thermal", "scale_asymmetry", "scale_nonlinearity", "misalignment", "time_offset")
        and res.kind == "still"
    ):
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
    open_search: bool = True,
    max_open_steps: int = 8,
    seed: int = 0,
) -> LoopResult:
    """Run the loop on a prepared :class:`~gyrocore.loop.residual.Residual` (see :func:`run_loop`).

    ``rebuild(recording) -> Residual`` (optional) rebuilds the residual from a recording; it
    enables the Gauss–Newton refinement of ``time_offset`` and the sample-level removal of
    narrow-band lines (see :func:`run_loop`).
    """
    declared = E.check_effect_names(declared)
    notes = list(res.notes)
    ignored = [d for d in declared if not _fittable(d)]
    if ignored:
        notes.append(f"declared effects without linear regressors are not fitted: {', '.join(ignored)}")
    model_effects = [d for d in declared if _fittable(d)]
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
    do_open = bool(open_search) and res.kind != "angles"
    if open_search and not do_open:
        notes.append(
            "open search not run: a known-angle reference has a few rotation windows, too few to "
            "describe effects outside the catalogue"
        )
    # family-wise error: a weighted Bonferroni/Holm split of alpha between the catalogue and the
    # three open-search kinds (search.ALPHA_SHARE); without the open search the catalogue has all of it
    alpha_cat = alpha * (S.ALPHA_SHARE["catalogue"] if do_open else 1.0)
    rng = np.random.default_rng(seed)

    rec0 = rec
    tau_acc = 0.0
    # sample-level line terms removed from the gyro (raw time frame): name -> [(axis, f_hz,
    # a_cos, a_sin), ...]; the correction is stream.held_correction (on the fly for a spill)
    held: dict[str, list] = {}
    held_params: dict[str, dict] = {}

    def base_rec():
        if not held:
            return rec0
        if isinstance(rec0, SpilledRecording):
            return rec0.with_ops(held=held, tau_s=0.0)
        from dataclasses import replace

        return replace(rec0, gyro_rad_s=rec0.gyro_rad_s - held_correction(rec0.t_s, held))

    def refit(res, model, rec, tau_acc, force_rebuild=False):
        """Joint fit; with time_offset in the model, re-linearise around its estimate."""
        if force_rebuild:
            rb = base_rec()
            rec = _advance(rb, tau_acc) if tau_acc != 0.0 else rb
            res = rebuild(rec)
            model = _Model(res, orders)
        fit, e = model.fit(model_effects)
        if rebuild is None or "time_offset" not in model_effects or res.kind not in ("rate", "attitude"):
            return res, model, rec, tau_acc, fit, e
        for _ in range(_TAU_ITERATIONS):
            d = float(fit.effect_theta("time_offset")[0])
            if not np.isfinite(d) or abs(d) < _TAU_TOL_S:
                break
            tau_acc += d
            rec = _advance(base_rec(), tau_acc)
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
    unexplained: list[Unexplained] = []
    last_tests: dict[str, Evidence] = {}
    open_last: dict = {}
    n_cat = 0

    def practical(ev: Evidence) -> bool:
        # out of sample (2-fold blocked): an effect fitted to coloured noise does not
        # predict the other folds; and of a size that matters, in the residual or in the
        # attitude
        size = ev.rms_reduction >= min_rms_reduction or (
            np.isfinite(ev.attitude_reduction) and ev.attitude_reduction >= min_attitude_reduction
        )
        held_ = ev.cv_rms_reduction > 0 or not np.isfinite(ev.cv_rms_reduction)
        if res.kind == "angles" and np.isfinite(ev.attitude_reduction):
            # the known angles are the reference: an effect that makes them worse by more
            # than a quarter of their uncertainty is refuted
            worse_deg = -ev.attitude_reduction * att_cur
            held_ = held_ and worse_deg <= 0.25 * np.degrees(res.angle_sigma_rad)
        return held_ and size

    def with_attitude(ev: Evidence, f, added: list[str]) -> Evidence:
        att = attitude_error_deg(res, rec, model.correction(f, model_effects + added))
        att_red = 1.0 - att / att_cur if att_cur > _MIN_ATTITUDE_DEG else float("nan")
        return Evidence(**{**ev.__dict__, "attitude_reduction": att_red})

    def open_term_test(name: str, thr: float, cv_base: float):
        """Full joint refit + HAC Wald test of an open term (as a catalogue candidate)."""
        ev, f = _test(model, model_effects, name, thr, rms_cur, e, cv_base)
        if ev.df1 > 0 and ev.p_value < thr:
            ev = with_attitude(ev, f, [name])
        return ev, f

    def step_screen_now(thr_step: float):
        X0 = model.design(model_effects)[0]
        sig = fit.axis_sigma_rad_s if fit is not None else np.maximum(np.std(e, axis=0), 1e-12)
        return S.screen_step(res, X0, e, sig, threshold=thr_step, rng=rng)

    def add_open(
        kind: str,
        axis: int,
        name: str,
        fields: dict,
        evidence: dict,
        before: float,
        after: float,
        att_b: float,
        att_a: float,
    ) -> None:
        unexplained.append(
            Unexplained(
                kind=kind,
                axis="xyz"[axis],
                effect=name,
                fields=fields,
                evidence=evidence,
                residual_rms_before_rad_s=before,
                residual_rms_after_rad_s=after,
                attitude_error_before_deg=att_b,
                attitude_error_after_deg=att_a,
            )
        )

    def ev_dict(ev: Evidence) -> dict:
        return {
            "statistic": ev.statistic,
            "df1": ev.df1,
            "df2": ev.df2,
            "p_value": ev.p_value,
            "log10_p": ev.log10_p,
            "threshold": ev.threshold,
            "cv_rms_reduction": ev.cv_rms_reduction,
            "rms_reduction": ev.rms_reduction,
            "attitude_reduction": ev.attitude_reduction,
            "params": ev.params,
            "std_errors": ev.std_errors,
            "hac_log10_p": ev.hac_log10_p,
            "model_log10_p": ev.model_log10_p,
        }

    for _ in range(max_steps + max_open_steps):
        remaining = [c for c in cands if c not in model_effects]
        cv_base = _cv_rms(res.y_rad_s, model.design(model_effects)[0], min_windows=_cv_min(res))
        sig: list[str] = []
        evs: dict[str, Evidence] = {}
        if remaining and n_cat < max_steps:
            trial = {c: _test(model, model_effects, c, 0.0, rms_cur, e, cv_base) for c in remaining}
            testable = [c for c in remaining if trial[c][0].df1 > 0]
            for c in remaining:
                if c not in testable:
                    untestable[c] = "not observable given the model: " + ", ".join(trial[c][0].unobservable)
            if testable:
                thr = alpha_cat / len(testable)
                for c in testable:
                    ev, f = trial[c]
                    ev = Evidence(**{**ev.__dict__, "threshold": thr})
                    if ev.p_value < thr:
                        ev = with_attitude(ev, f, _with_companion(model_effects, c))
                    evs[c] = ev
                sig = [c for c in testable if evs[c].p_value < thr and practical(evs[c])]
                last_tests = evs
        if sig:
            sig.sort(key=lambda c: (evs[c].log10_p, -evs[c].statistic))
            best = sig[0]
            ambiguous, nested = [], []
            thr = evs[best].threshold
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
            if best == "bias_ramp" and do_open:
                # step vs ramp: a bias step also correlates with time; model comparison decides
                thr_step = alpha * S.ALPHA_SHARE["step"]
                st = step_screen_now(thr_step)
                if st is not None and st.p_value < thr_step:
                    name = S.canonical(f"step[{S._fmt_num(st.t_s)}]")
                    ev_s, f_s = open_term_test(name, thr_step, cv_base)
                    X0 = model.design(model_effects)[0]
                    cv_step = _cv_rms(
                        res.y_rad_s, np.concatenate([X0, model.block(name)[1]], axis=2), min_windows=_cv_min(res)
                    )
                    cv_ramp = _cv_rms(
                        res.y_rad_s, np.concatenate([X0, model.block("bias_ramp")[1]], axis=2), min_windows=_cv_min(res)
                    )
                    if cv_step < cv_ramp and ev_s.df1 > 0 and practical(ev_s):
                        model_effects.append(name)
                        res, model, rec, tau_acc, fit, e = refit(res, model, rec, tau_acc)
                        rms_new = _rms(e)
                        att_new = attitude_error_deg(res, rec, model.correction(fit, model_effects))
                        size = np.array([fit.effect_theta(name)[i] for i in range(3)])
                        se = np.array([fit.effect_stderr(name)[i] for i in range(3)])
                        ax = int(np.argmax(np.abs(size) / np.where(se > 0, se, np.inf)))
                        evd = ev_dict(ev_s)
                        evd.update(
                            {
                                "sup_statistic": st.statistic,
                                "bootstrap_p": st.p_value,
                                "n_boot": st.n_boot,
                                "n_candidates": st.n_candidates,
                                "log10_p_step": st.log10_p,
                                "threshold_step": thr_step,
                                "vs_ramp": {
                                    "cv_rms_step_rad_s": cv_step,
                                    "cv_rms_ramp_rad_s": cv_ramp,
                                    "chosen": "step",
                                },
                                "size_std_errors_rad_s": se,
                            }
                        )
                        add_open(
                            "step",
                            ax,
                            name,
                            {"t_s": st.t_s, "size_rad_s": size},
                            evd,
                            rms_cur,
                            rms_new,
                            att_cur,
                            att_new,
                        )
                        notes.append(
                            f"a bias step at t = {st.t_s:.6g} s explains the residual better than "
                            f"bias_ramp (out-of-sample RMS {cv_step:.3g} vs {cv_ramp:.3g} rad/s)"
                        )
                        history.append(e)
                        rms_cur, att_cur = rms_new, att_new
                        last_tests = {}
                        continue
            # `best` has the strongest evidence (smallest p-value, which accounts for its number
            # of parameters); the ambiguous ones are reported with it.
            model_effects.extend(_with_companion(model_effects, best))
            res, model, rec, tau_acc, fit, e = refit(res, model, rec, tau_acc)
            history.append(e)
            rms_new = _rms(e)
            att_new = attitude_error_deg(res, rec, model.correction(fit, model_effects))
            evb = evs[best]
            steps.append(
                Step(
                    effect=best,
                    evidence=Evidence(**{**evb.__dict__, "ambiguous_with": tuple(ambiguous)}),
                    residual_rms_before_rad_s=rms_cur,
                    residual_rms_after_rad_s=rms_new,
                    attitude_error_before_deg=att_cur,
                    attitude_error_after_deg=att_new,
                )
            )
            n_cat += 1
            last_tests = {}
            rms_cur, att_cur = rms_new, att_new
            continue
        # ------------------------------------------------------------ open search
        if not do_open or len(unexplained) >= max_open_steps:
            break
        took = _open_step(
            res=res,
            rec=rec,
            model=model,
            model_effects=model_effects,
            fit=fit,
            e=e,
            alpha=alpha,
            rms_cur=rms_cur,
            att_cur=att_cur,
            cv_base=cv_base,
            open_term_test=open_term_test,
            practical=practical,
            step_screen_now=step_screen_now,
            ev_dict=ev_dict,
            untestable=untestable,
            held=held,
            tau_acc=tau_acc,
            can_hold=rebuild is not None,
            open_last=open_last,
        )
        if took is None:
            break
        kind, axis, name, fields, evd, held_corr = took
        if held_corr is not None:
            # a sample-level line: removed from the gyro (raw time frame), residual rebuilt
            x_before = evd.pop("_sample_rms_before")
            held.setdefault(name, []).append(held_corr)
            hp = held_params.setdefault(name, {})
            for k_, v_ in evd.pop("_params").items():
                hp[k_] = v_
            res, model, rec, tau_acc, fit, e = refit(res, model, rec, tau_acc, force_rebuild=True)
            x_after = evd.pop("_sample_rms_after")
            rms_new = _rms(e)
            att_new = attitude_error_deg(res, rec, model.correction(fit, model_effects))
            evd["window_residual_rms_before_rad_s"] = rms_cur
            evd["window_residual_rms_after_rad_s"] = rms_new
            add_open(kind, axis, name, fields, evd, x_before, x_after, att_cur, att_new)
        else:
            model_effects.append(name if axis is None or kind == "step" else f"{name}@{axis}")
            res, model, rec, tau_acc, fit, e = refit(res, model, rec, tau_acc)
            rms_new = _rms(e)
            att_new = attitude_error_deg(res, rec, model.correction(fit, model_effects))
            if kind == "step":
                size = np.array(fit.effect_theta(name), float)
                se = np.array(fit.effect_stderr(name), float)
                fields = dict(fields, size_rad_s=size)
                evd["size_std_errors_rad_s"] = se
                axis = int(np.argmax(np.abs(size) / np.where(se > 0, se, np.inf)))
            elif kind == "regressor":
                fields = dict(fields, coef=float(fit.effect_theta(f"{name}@{axis}")[0]))
            add_open(kind, axis, name, fields, evd, rms_cur, rms_new, att_cur, att_new)
        history.append(e)
        rms_cur, att_cur = rms_new, att_new
    found = [s.effect for s in steps]
    params = _params_table(fit, model_effects)
    for name, hp in held_params.items():
        params[name] = {k: [float(v[0]), float(v[1])] for k, v in hp.items()}
    if tau_acc != 0.0 and "time_offset" in params:
        v, se = params["time_offset"]["tau_s"]
        params["time_offset"]["tau_s"] = [tau_acc + v, se]
        notes.append(
            f"time_offset re-linearised (Gauss-Newton): the gyro was advanced by {tau_acc:.6g} s and "
            "the fit repeated; tau_s is the total"
        )
    t0_c = res.temp_mean_c()
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
        unexplained=tuple(unexplained),
        open_search=open_last,
        t0_c=t0_c,
    )


def _line_series(res: Residual, rec: Recording, correction: np.ndarray):
    """The series the line search runs on: (x (n, 3), t (n,), fs, reference motion (n, R) or
    None, level, sample slice or None).

    ``rate``: the sample-level residual gyro − ω_ref − model (longest run with a finite
    reference); ``still``: gyro − model over the longest contiguous run of still windows;
    ``attitude``: the window residual (no sample-level reference: the optical attitude is
    never differentiated), longest evenly spaced run.
    """
    t = rec.t_s
    if isinstance(rec, SpilledRecording):
        # from disk (rate reference, finite everywhere: stream._build_spilled): the residual
        # and the motion columns a window at a time
        if res.kind != "rate":  # pragma: no cover
            return None
        ref, acc = rec.ref_rate_rad_s, rec.accel_m_s2

        def x_rows(a, b):
            return rec.gyro_rad_s.rows(a, b) - ref.rows(a, b) - rows_of(correction, a, b)

        def m_rows(a, b):
            return (
                ref.rows(a, b)
                if acc is None
                else np.concatenate([ref.rows(a, b), np.nan_to_num(acc.rows(a, b))], axis=1)
            )

        return (
            Rows(x_rows, rec.n, 3),
            t,
            rec.rate_hz,
            Rows(m_rows, rec.n, 3 if acc is None else 6),
            "sample",
            slice(0, rec.n),
        )
    if res.kind == "rate":
        ref = rec.ref_rate_rad_s
        ok = np.all(np.isfinite(ref), axis=1)
        a, b = _longest_run(ok)
        sl = slice(a, b)
        x = rec.gyro_rad_s[sl] - ref[sl] - correction[sl]
        mot = [ref[sl]]  # (a line of the rate is a line of its derivative too)
        if rec.accel_m_s2 is not None:
            mot.append(np.nan_to_num(rec.accel_m_s2[sl]))
        return x, t[sl], rec.rate_hz, np.concatenate(mot, axis=1), "sample", sl
    if res.kind == "still":
        a_w, b_w = res.win_start, res.win_stop
        cont = np.concatenate([[False], a_w[1:] == b_w[:-1]])
        best, cur, st, bst = 0, 0, 0, 0
        for k in range(res.m):
            if k > 0 and cont[k]:
                cur += 1
            else:
                cur, st = 1, k
            if cur > best:
                best, bst = cur, st
        sl = slice(int(a_w[bst]) + 1, int(b_w[bst + best - 1]) + 1)
        x = rec.gyro_rad_s[sl] - correction[sl]
        mot = np.nan_to_num(rec.accel_m_s2[sl]) if rec.accel_m_s2 is not None else None
        return x, t[sl], rec.rate_hz, mot, "sample", sl
    if res.kind == "attitude":
        return _attitude_line_series(rec, correction)
    return None


#: Segments the sample-level attitude residual is cut into for the pooled line test
#: (:func:`gyrocore.search.even_segments`).
ATTITUDE_LINE_SEGMENTS = 8


def _attitude_line_series(rec: Recording, correction: np.ndarray):
    """Sample-level residual against a reference attitude, for the line search.

    The reference is differentiated, ω_ref,k = rotvec(R_{k−1}ᵀR_k)/Δt_k, and the residual is
    e_k = rotvec(ΔR_refᵀ·exp((gyro_k − model_k)·Δt_k))/Δt_k
    (:func:`gyrocore.attitude.rate_error_vs_attitude`) on the samples whose reference is
    valid at both ends of a regular interval; those are cut into equal segments
    (:func:`gyrocore.search.even_segments`) that never straddle a dropout. White attitude
    noise σ_q of the reference becomes rate noise of one-sided PSD 8σ_q²·fs·sin²(πf/fs)
    (∝ f² below fs/4): the F-test's local noise estimate carries it, so the test stays
    valid and only loses power where it dominates the gyro's own noise (docs/loop.md §6).
    Needs the reference on the gyro's rows (a reference sampled more slowly than the gyro,
    NaN between its frames, would alias the gyro's lines above its Nyquist frequency onto
    its grid): None otherwise, and the window-level test alone runs.

    Returns (x (S·L, 3), t (S·L,), fs, motion columns (S·L, 3 or 6), "sample", sample
    indices, L) or None.
    """
    if isinstance(rec, SpilledRecording) or rec.ref_quat_wxyz is None:
        return None
    t = rec.t_s
    e, w_ref, valid = rate_error_vs_attitude(t, rec.ref_quat_wxyz, rec.gyro_rad_s - correction)
    ok_q = np.all(np.isfinite(rec.ref_quat_wxyz), axis=1)
    # the reference must be on (nearly) every gyro row where it is tracked: adjacent valid
    # rows are its own consecutive frames (not every 4th row of a 1-kHz gyro)
    if valid.sum() < 0.5 * ok_q.sum():
        return None
    idx, L = S.even_segments(t, valid, n_target=ATTITUDE_LINE_SEGMENTS)
    if idx.size == 0:
        return None
    tt = t[idx]
    fs = 1.0 / float(np.median(np.diff(t)[idx[1:] - 1]))
    mot = [w_ref[idx]]
    if rec.accel_m_s2 is not None:
        mot.append(np.nan_to_num(rec.accel_m_s2[idx]))
    return e[idx], tt, fs, np.concatenate(mot, axis=1), "sample", idx, L


def _longest_run(ok: np.ndarray) -> tuple[int, int]:
    m = np.concatenate([[False], ok, [False]]).astype(np.int8)
    d = np.diff(m)
    a, b = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    if a.size == 0:
        return 0, 0
    j = int(np.argmax(b - a))
    return int(a[j]), int(b[j])


def _window_line_series(res: Residual, e: np.ndarray):
    """Longest evenly spaced run of windows of the window residual: (x, t_mid, fs, idx)."""
    T = res.duration_s
    win = float(np.median(T))
    even = np.concatenate(
        [[False], (np.abs(np.diff(res.t_mid_s) - win) <= 0.05 * win) & (np.abs(T[1:] - win) <= 0.05 * win)]
    )
    best, cur, st, bst = 0, 0, 0, 0
    for k in range(res.m):
        if k > 0 and even[k]:
            cur += 1
        else:
            cur, st = 1, k
        if cur > best:
            best, bst = cur, st
    idx = np.arange(bst, bst + best)
    return e[idx], res.t_mid_s[idx], 1.0 / win, idx


def _open_step(
    *,
    res,
    rec,
    model,
    model_effects,
    fit,
    e,
    alpha,
    rms_cur,
    att_cur,
    cv_base,
    open_term_test,
    practical,
    step_screen_now,
    ev_dict,
    untestable,
    held,
    tau_acc,
    can_hold,
    open_last,
):
    """One step of the open search: the strongest significant description among the regressor
    library, lines and a bias step, or None. See :mod:`gyrocore.loop.search`.

    Returns (kind, axis, effect name, fields, evidence, held line (axis, f_hz, a_cos, a_sin) or None).
    """
    options = []  # (log10 p − log10 threshold, payload)
    sig = fit.axis_sigma_rad_s if fit is not None else np.maximum(np.std(e, axis=0), 1e-12)
    X0 = model.design(model_effects)[0]
    n_par = fit.rank if fit is not None else 0
    # ---------------- regressor library
    terms = S.library_terms(res.inputs, kind=res.kind, chunks=(res.iter_inputs(context=1) if res.chunked() else None))
    exclude = set()
    for term in terms:
        for i in range(3):
            eq = S.catalogue_equivalent(term, i)
            if eq is not None or f"regressor[{term}]@{i}" in model_effects:
                exclude.add((term, i))
    Xlib = S.library_windows(res, terms) if terms else None
    # a product that is numerically one of its factors on this recording (f_x*t in a still
    # log is a ramp t) is that factor: screened under the factor's own name, or, when the
    # factor is a catalogue term, already tested (and kept or refused) as that effect
    equiv = {}
    if terms:
        for (term, i), simple in S.collinear_simpler(res, X0, sig, terms, Xlib).items():
            if (term, i) in exclude:
                continue
            exclude.add((term, i))
            cat = S.catalogue_equivalent(simple, i)
            equiv[f"{term}@{'xyz'[i]}"] = (
                f"{cat} (tested in the catalogue step)" if cat is not None else f"regressor[{simple}]"
            )
    lib = S.screen_library(res, X0, e, sig, terms, exclude, n_par, Xlib) if terms else None
    if lib is not None:
        thr = alpha * S.ALPHA_SHARE["regressor"] / lib.n_tested
        open_last["regressor"] = {
            "term": lib.term,
            "axis": "xyz"[lib.axis],
            "score_F": lib.statistic,
            "log10_p": lib.log10_p,
            "threshold": thr,
            "n_tested": lib.n_tested,
        }
        if equiv:
            open_last["regressor"]["collinear_with_simpler"] = equiv
        if lib.p_value < thr:
            name = S.canonical(f"regressor[{lib.term}]")
            ev, _ = open_term_test(f"{name}@{lib.axis}", thr, cv_base)
            open_last["regressor"].update(
                {"wald_log10_p": ev.log10_p, "cv_rms_reduction": ev.cv_rms_reduction, "rms_reduction": ev.rms_reduction}
            )
            if ev.df1 > 0 and ev.p_value < thr and practical(ev):
                evd = ev_dict(ev)
                evd.update(
                    {
                        "score_F": lib.statistic,
                        "score_log10_p": lib.log10_p,
                        "n_tested": lib.n_tested,
                        "residual": "window",
                    }
                )
                options.append(
                    (ev.log10_p - np.log10(thr), ("regressor", lib.axis, name, {"term": lib.term}, evd, None))
                )
    elif not terms:
        open_last["regressor"] = {"skipped": "no signal varies in the data"}
    # ---------------- lines
    thr_line = alpha * S.ALPHA_SHARE["periodic"] / 3.0
    corr = model.correction(fit, model_effects)
    ser = _line_series(res, rec, corr) if can_hold else None
    # against an attitude reference both the sample level (differentiated reference) and the
    # window level (below the sample level's lowest frequency) are searched: half of α each
    both = res.kind == "attitude" and ser is not None and ser[0].shape[0] >= 256
    if res.kind == "attitude" and can_hold and not both:
        open_last["periodic_sample_level"] = (
            "not run: the reference attitude is not on the gyro's rows (sampled more slowly: the gyro's lines above "
            "its Nyquist frequency would alias) or has no gap-free run of 512 samples; window level only"
        )
    thr_sample = thr_line / 2 if both else thr_line
    if ser is not None and ser[0].shape[0] >= 256:
        x, tt, fs, mot, level, _ = ser[:6]
        seg_len = ser[6] if len(ser) > 6 else S.segment_length(x.shape[0])
        # (axis, frequency) already removed
        done = [
            (i, float(n[len("periodic[") : -1]))
            for n, ls in held.items()
            for i in range(3)
            if any(ax == i and (a_ != 0 or b_ != 0) for ax, _, a_, b_ in ls)
        ]
        lines = S.screen_lines(x, fs, ref=mot, skip=done, seg_max=seg_len)
        open_last["periodic"] = [
            {
                "axis": "xyz"[l.axis],
                "frequency_hz": l.frequency_hz,
                "F": l.statistic,
                "log10_p": l.log10_p,
                "threshold": thr_sample,
                "n_freq": l.n_freq,
                "bandwidth_hz": l.bandwidth_hz,
                "masked_by_motion_bins": l.masked_by_motion,
                "level": "sample",
            }
            for l in lines
        ]
        for l in lines:
            if l.log10_p >= np.log10(thr_sample):
                continue
            i = l.axis
            # one axis of the sample-level residual at a time (a recording on disk: read and
            # corrected a window at a time into one (n,) array)
            xi = x.axis(i) if isinstance(x, Rows) else x[:, i]
            # ± one bin of the segment grid (fs/L)
            f = S.round_frequency(S.refine_frequency(xi, tt, l.frequency_hz, fs / seg_len))
            cv = S.sinusoid_cv_reduction(xi, tt, f)
            if not cv > 0:
                continue
            name = S.canonical(f"periodic[{S._fmt_num(f)}]")
            coef, se = S.fit_sinusoid(xi, tt, f)
            a, b = float(coef[0, 0]), float(coef[1, 0])
            before, after = S.sinusoid_rms(xi, tt, f, a, b)
            del xi
            # raw time frame: the residual is of the gyro advanced by tau (time_offset)
            phi = 2 * np.pi * f * tau_acc
            a_raw, b_raw = a * np.cos(phi) - b * np.sin(phi), a * np.sin(phi) + b * np.cos(phi)
            corr_full = (i, f, a_raw, b_raw)  # stream.held_correction
            evd = {
                "statistic": l.statistic,
                "df1": l.df1,
                "df2": l.df2,
                "log10_p": l.log10_p,
                "p_value": 10**l.log10_p,
                "threshold": thr_sample,
                "n_frequencies_tested": l.n_freq,
                "bandwidth_hz": l.bandwidth_hz,
                "grid_frequency_hz": l.frequency_hz,
                "cv_rms_reduction": cv,
                "residual": level,
                "test": "Thomson multitaper harmonic F (NW 4, K 7)",
                "params": {f"a_cos_rad_s[{i}]": a_raw, f"a_sin_rad_s[{i}]": b_raw},
                "std_errors": {f"a_cos_rad_s[{i}]": float(se[0, 0]), f"a_sin_rad_s[{i}]": float(se[1, 0])},
                "_sample_rms_before": before,
                "_sample_rms_after": after,
                "_params": {
                    f"a_cos_rad_s[{i}]": (a_raw, float(se[0, 0])),
                    f"a_sin_rad_s[{i}]": (b_raw, float(se[1, 0])),
                },
            }
            fields = {"frequency_hz": f, "amplitude_rad_s": float(np.hypot(a, b))}
            if res.kind == "attitude":
                evd["segments"] = {"n": int(x.shape[0] // seg_len), "length": int(seg_len)}
            options.append((l.log10_p - np.log10(thr_sample), ("periodic", i, name, fields, evd, corr_full)))
    if res.kind == "attitude" and res.m >= 64:
        thr_line = thr_line / 2 if both else thr_line
        x, tt, fs, idx = _window_line_series(res, e)
        if x.shape[0] >= 64:
            mot = res.window_mean(np.asarray(res.inputs.omega_S_rad_s, float))[idx]
            done = [
                (column_axis("a[" + k.split("@")[1] + "]"), float(k[len("periodic[") : k.index("]")]))
                for k in model_effects
                if k.startswith("periodic[")
            ]
            lines = S.screen_lines(x, fs, ref=mot, skip=done)
            open_last["periodic"] = open_last.get("periodic", []) if both else []
            open_last["periodic"] += [
                {
                    "axis": "xyz"[l.axis],
                    "frequency_hz": l.frequency_hz,
                    "F": l.statistic,
                    "log10_p": l.log10_p,
                    "threshold": thr_line,
                    "n_freq": l.n_freq,
                    "level": "window",
                }
                for l in lines
            ]
            for l in lines:
                if l.log10_p >= np.log10(thr_line):
                    continue
                f = S.round_frequency(S.refine_frequency(x[:, l.axis], tt, l.frequency_hz, 2 * l.bandwidth_hz))
                name = S.canonical(f"periodic[{S._fmt_num(f)}]")
                ev, _ = open_term_test(f"{name}@{l.axis}", thr_line, cv_base)
                # the harmonic F decided significance; the window refit must hold out of sample
                if ev.df1 > 0 and (ev.cv_rms_reduction > 0 or not np.isfinite(ev.cv_rms_reduction)):
                    evd = ev_dict(ev)
                    evd.update(
                        {
                            "line_F": l.statistic,
                            "line_log10_p": l.log10_p,
                            "threshold": thr_line,
                            "residual": "window",
                            "n_frequencies_tested": l.n_freq,
                        }
                    )
                    a = ev.params.get(f"a_cos_rad_s[{l.axis}]", 0.0)
                    b = ev.params.get(f"a_sin_rad_s[{l.axis}]", 0.0)
                    options.append(
                        (
                            l.log10_p - np.log10(thr_line),
                            (
                                "periodic",
                                l.axis,
                                name,
                                {"frequency_hz": f, "amplitude_rad_s": float(np.hypot(a, b))},
                                evd,
                                None,
                            ),
                        )
                    )
    # ---------------- step
    thr_step = alpha * S.ALPHA_SHARE["step"]
    st = step_screen_now(thr_step)
    if st is not None:
        open_last["step"] = {
            "t_s": st.t_s,
            "sup_statistic": st.statistic,
            "bootstrap_p": st.p_value,
            "threshold": thr_step,
            "n_boot": st.n_boot,
            "n_candidates": st.n_candidates,
        }
        if st.p_value < thr_step:
            name = S.canonical(f"step[{S._fmt_num(st.t_s)}]")
            if name not in model_effects:
                ev, _ = open_term_test(name, thr_step, cv_base)
                if ev.df1 > 0 and practical(ev):
                    X0c = model.design(model_effects)[0]
                    cv_step = _cv_rms(
                        res.y_rad_s, np.concatenate([X0c, model.block(name)[1]], axis=2), min_windows=_cv_min(res)
                    )
                    evd = ev_dict(ev)
                    evd.update(
                        {
                            "sup_statistic": st.statistic,
                            "bootstrap_p": st.p_value,
                            "n_boot": st.n_boot,
                            "n_candidates": st.n_candidates,
                            "threshold_step": thr_step,
                            "residual": "window",
                        }
                    )
                    if "bias_ramp" not in model_effects:
                        cv_ramp = _cv_rms(
                            res.y_rad_s,
                            np.concatenate([X0c, model.block("bias_ramp")[1]], axis=2),
                            min_windows=_cv_min(res),
                        )
                        evd["vs_ramp"] = {
                            "cv_rms_step_rad_s": cv_step,
                            "cv_rms_ramp_rad_s": cv_ramp,
                            "chosen": "step" if cv_step <= cv_ramp else "ramp",
                        }
                    options.append(
                        (np.log10(st.p_value) - np.log10(thr_step), ("step", 0, name, {"t_s": st.t_s}, evd, None))
                    )
    if not options:
        return None
    options.sort(key=lambda o: o[0])
    return options[0][1]


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
    open_search: bool = True,
    seed: int = 0,
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
        Still / known-rotation segments (see :mod:`gyrocore.loop.residual`).
    candidates : sequence of str, optional
        Effects to trace (default: every :data:`CANDIDATES` entry not declared).
    reference : {"auto", "rate", "attitude", "still", "angles"}
    window_s : float, optional
        Observation window length, s (default: see :func:`gyrocore.loop.residual.build_residual`).
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
        axis only (free hand turns); see :func:`gyrocore.loop.residual.build_residual`.

    open_search : bool
        After the catalogue, describe what is still significant outside it (regressor
        library, narrow-band lines, bias steps: :mod:`gyrocore.loop.search`); α is then split
        between the catalogue (½) and the three open kinds (⅙ each).
    seed : int
        Seed of the step test's parametric bootstrap.

    Returns
    -------
    LoopResult
    """
    if not 0 < alpha < 1:
        raise GyroInputError(f"alpha must be in (0, 1), not {alpha}")
    with _single_thread():
        res = build_residual(
            rec,
            reference=reference,
            segments=segments,
            window_s=window_s,
            angle_sigma_deg=angle_sigma_deg,
            axis_sigma_deg=axis_sigma_deg,
            angle_mode=angle_mode,
        )

        def rebuild(r: Recording) -> Residual:
            return build_residual(
                r,
                reference=res.kind,
                segments=segments,
                window_s=window_s,
                angle_sigma_deg=angle_sigma_deg,
                axis_sigma_deg=axis_sigma_deg,
                angle_mode=angle_mode,
            )

        return loop_residual(
            res,
            rec,
            declared=declared,
            candidates=candidates,
            alpha=alpha,
            thermal_order=thermal_order,
            rebuild=rebuild,
            min_rms_reduction=min_rms_reduction,
            min_attitude_reduction=min_attitude_reduction,
            max_steps=max_steps,
            open_search=open_search,
            seed=seed,
        )


# ---------------------------------------------------------------------------- plots
_NATURAL = {
    "bias_ramp": ("time since start, s", lambda r: np.repeat(r.t_mid_s[:, None] - r.inputs.t_s[0], 3, axis=1)),
    "bias_thermal": (
        "temperature, °C",
        lambda r: np.repeat(
            r.window_mean(np.repeat(np.asarray(r.inputs.temp_c, float)[:, None], 3, axis=1))[:, :1], 3, axis=1
        ),
    ),
    "bias_temp_rate": (
        "dT/dt, °C/s",
        lambda r: np.repeat(r.window_mean(np.repeat(r.inputs.temp_rate_c_s()[:, None], 3, axis=1))[:, :1], 3, axis=1),
    ),
    "scale": ("reference rate, rad/s", lambda r: r.window_mean(_as_rows(r.inputs.omega_S_rad_s))),
    "scale_asymmetry": ("reference rate, rad/s", lambda r: r.window_mean(_as_rows(r.inputs.omega_S_rad_s))),
    "scale_nonlinearity": ("reference rate, rad/s", lambda r: r.window_mean(_as_rows(r.inputs.omega_S_rad_s))),
    "time_offset": (
        "rate derivative dω/dt, rad/s²",
        lambda r: r.window_mean(
            np.gradient(np.asarray(r.inputs.omega_S_rad_s, float), np.asarray(r.inputs.t_s, float), axis=0)
        ),
    ),
}


def _as_rows(v):
    return v if isinstance(v, Rows) else np.asarray(v, float)


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

    from gyrocore.data.recording import atomic_write_bytes
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
            th = np.array(
                [
                    step.evidence.params[n]
                    for n in step.evidence.params
                    if not n.startswith("bias.") and not n.startswith("scale.")
                ]
            )
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
        fig.suptitle(
            f"step {k + 1}: {eff} (F = {ev.statistic:.3g}, log10 p = {ev.log10_p:.3g}); "
            f"RMS {step.residual_rms_before_rad_s * D:.3g} -> {step.residual_rms_after_rad_s * D:.3g} deg/s"
        )
        fig.tight_layout()
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=90)
        plt.close(fig)
        p = out / f"{prefix}_step{k + 1}_{eff}.png"
        atomic_write_bytes(p, buf.getvalue())
        paths.append(p)
    return paths


# ---------------------------------------------------------------------------- the model leaves the recording
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
            r = _advance(r, tau)
        res = build_residual(r, reference=reference, segments=segments, window_s=window_s)
        corr = model_correction(res, params)
        y = res.y_rad_s - res.window_mean(corr)
        if refit_bias:
            _, Xb = res.regressors("bias")
            th, *_ = np.linalg.lstsq(Xb.reshape(-1, 3), y.reshape(-1), rcond=None)
            y = y - np.einsum("mip,p->mi", Xb, th)
            corr = corr + th[None, :]
        out[f"residual_rms_{tag}_rad_s"] = _rms(y)
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
        f = float(S.parse_family(name)[1])
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
        f = float(S.parse_family(name)[1])
        row = {"effect": name, "frequency_hz": f}
        for tag in ("before", "after"):
            t, e, ok = sample[tag]
            coef, se = S.fit_sinusoid(e[ok], t[ok], f)
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
