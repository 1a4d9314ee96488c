"""The IEEE Std 952 joint fit of the Allan variance with backward elimination (``--method adev_legacy``).

σ²(τ) = 3Q²/τ² + N²/τ + (2 ln2/π)B² + K²τ/3 + R²τ²/2 (Q angle quantization [rad], N angle random
walk [rad/√s], B bias instability [rad/s], K rate random walk [rad/s/√s], R rate ramp [rad/s²];
IEEE Std 952-1997 annex C) fitted **jointly** by non-negative weighted least squares on the
overlapping Allan variance at octave factors up to T/4, with the correlation of the estimates
between τ (:func:`avar_correlation_white`, :func:`avar_correlation_model`) and Greenhall's EDF;
:func:`select_ieee952` drops the terms the data cannot resolve. Kept as the noise study's
baseline; the default estimator is the GMWM (:mod:`gyrocore.noise.gmwm`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.linalg
import scipy.optimize
import scipy.stats

from . import avar as AV
from .model import IEEE_TERMS

__all__ = ["ieee952_design", "avar_correlation_white", "avar_correlation_model", "fit_ieee952", "select_ieee952"]

# Noise type α (S_y ∝ f^α) that dominates where each term dominates; used for the EDF.
# Q: white phase (angle) noise α=2; N: white rate α=0; B: flicker rate α=−1;
# K: random-walk rate α=−2; R: drift, treated as α=−2 (Greenhall needs α > −3 for AVAR).
_TERM_ALPHA = (2, 0, -1, -2, -2)
_B_FACTOR = 2.0 * math.log(2.0) / math.pi  # σ² = (2 ln2/π)·B² on the flat part
_Z95 = scipy.stats.norm.isf(0.025)
_LONG_TERMS = ("bias_instability_rad_s", "rrw_rad_per_s_sqrt_s", "rate_ramp_rad_s2")


def ieee952_design(taus_s: np.ndarray) -> np.ndarray:
    """Columns of σ²(τ) for coefficients c = (Q², N², B², K², R²); shape (M, 5)."""
    t = np.asarray(taus_s, float)
    return np.column_stack([3.0 / t**2, 1.0 / t, np.full_like(t, _B_FACTOR), t / 3.0, t**2 / 2.0])


_CORR_CACHE: dict[tuple, np.ndarray] = {}


def avar_correlation_white(m: np.ndarray, n_phase: int) -> np.ndarray:
    """Correlation matrix of overlapping AVAR estimates at factors ``m`` under white rate noise.

    σ̂²(m) ∝ Σ_k d_m(k)², d_m = h_m ∗ y with h_m = (−1 ×m, +1 ×m). For Gaussian y,
    Cov(Σ_k d_i(k)², Σ_l d_j(l)²) = 2 Σ_k Σ_l g_ij(k−l)², g_ij the cross-correlation of h_i
    and h_j (exact count of (k, l) pairs per lag). Octave-spaced points are far from
    independent (ρ ≈ 0.5–0.7 between neighbours); ignoring it makes the term intervals about
    1.6× too narrow (measured by Monte Carlo, tests/gyrocore/noise/test_allan.py).
    """
    import scipy.signal

    key = (tuple(int(v) for v in m), int(n_phase))
    hit = _CORR_CACHE.get(key)
    if hit is not None:
        return hit
    m = [int(v) for v in m]
    n = [n_phase - 2 * v for v in m]
    h = [np.concatenate([-np.ones(v), np.ones(v)]) for v in m]
    M = len(m)
    V = np.zeros((M, M))
    for i in range(M):
        for j in range(i, M):
            g = scipy.signal.fftconvolve(h[i], h[j][::-1])  # g[lag + len_j − 1]
            g = np.rint(g)  # integer counts; remove FFT round-off
            lags = np.arange(g.size) - (h[j].size - 1)  # g at lag = Cov(d_i(k), d_j(k + lag))
            # pairs (k, l = k + lag) with 0 ≤ k < n_i, 0 ≤ l < n_j
            pairs = np.clip(np.minimum(n[i], n[j] - lags) - np.maximum(0, -lags), 0, None)
            V[i, j] = V[j, i] = 2.0 * float(np.sum(pairs * g * g))
    d = np.sqrt(np.diag(V))
    R = V / np.outer(d, d)
    _CORR_CACHE[key] = R
    return R


_QF_CACHE: dict[tuple, np.ndarray] = {}
_QF_STACK: dict[tuple, np.ndarray] = {}
_MAX_RATIO = 1024  # pairs of τ further apart than this are taken as uncorrelated


def _pair_quadratic(mi: int, mj: int, n_phase: int, res: int = 16) -> np.ndarray:
    """Coefficients (A1..A6) of Cov(Σd_i², Σd_j²)/2 as a quadratic form in (a, b, c).

    a = white-rate variance per sample (N²·rate), b = rate-random-walk increment variance
    (K²·τ0), c = white-angle variance in rate units (Q²·rate²). d_m = Haar filter h_m (−1 ×m,
    +1 ×m) on the rate for a; its running sum, the triangle g_m(v) = min(v, 2m − v), on the
    random-walk increments for b; p_m = δ₀ − 2δ_m + δ₂m on the angle noise for c. With
    c_ij(lag) = a·X_hh + b·X_gg + c·X_pp (cross-correlations of the filters),
    Cov = 2 Σ_lag pairs(lag)·c_ij(lag)² = 2(a²A1 + b²A2 + c²A3 + 2abA4 + 2acA5 + 2bcA6).
    Long filters are evaluated on a grid of step s = min(m)/res (box sums are exact on it; the
    triangle's Riemann sum has O(1/res) error) — checked against Monte Carlo in the tests.
    """
    key = (mi, mj, n_phase, res)
    hit = _QF_CACHE.get(key)
    if hit is not None:
        return hit
    import scipy.signal

    s = max(1, min(mi, mj) // res)
    ni, nj = n_phase - 2 * mi, n_phase - 2 * mj

    def h_dec(mm: int) -> np.ndarray:
        L = mm // s
        return np.concatenate([-np.ones(L), np.ones(L)])

    def g_dec(mm: int) -> np.ndarray:
        v = np.arange(0, 2 * mm, s, dtype=float)
        return np.minimum(v, 2 * mm - v)

    hj = h_dec(mj)
    Wf = s * np.rint(scipy.signal.fftconvolve(h_dec(mi), hj[::-1]))
    Kf = s * scipy.signal.fftconvolve(g_dec(mi), g_dec(mj)[::-1])
    idx0 = hj.size - 1
    lags = (np.arange(Wf.size) - idx0) * s  # value at lag = Cov(d_i(k), d_j(k + lag))
    pairs = np.clip(np.minimum(ni, nj - lags) - np.maximum(0, -lags), 0, None).astype(float)
    A1 = s * float(np.sum(pairs * Wf * Wf))
    A2 = s * float(np.sum(pairs * Kf * Kf))
    A4 = s * float(np.sum(pairs * Wf * Kf))
    P: dict[int, float] = {}
    for u, pu in ((0, 1.0), (mi, -2.0), (2 * mi, 1.0)):
        for v, pv in ((0, 1.0), (mj, -2.0), (2 * mj, 1.0)):
            P[u - v] = P.get(u - v, 0.0) + pu * pv  # shared angle sample: l = k + (u − v)
    A3 = A5 = A6 = 0.0
    grid = np.arange(Wf.size)
    for lag, pv in P.items():
        if pv == 0.0:
            continue
        pr = max(0, min(ni, nj - lag) - max(0, -lag))
        k = lag / s + idx0
        A3 += pr * pv * pv
        A5 += pr * pv * float(np.interp(k, grid, Wf))
        A6 += pr * pv * float(np.interp(k, grid, Kf))
    out = np.array([A1, A2, A3, A4, A5, A6])
    _QF_CACHE[key] = out
    return out


def avar_correlation_model(m: np.ndarray, n_phase: int, rate_hz: float, coef: np.ndarray) -> np.ndarray:
    """Correlation of overlapping AVAR estimates for white rate + rate random walk + white angle.

    ``coef`` = (Q², N², B², K², R²) of the current fit; B and R do not enter (flicker has no
    finite-filter form; a ramp is deterministic). Pure white noise when N = K = Q = 0.
    Random walk correlates the octave points far more than white noise (neighbours ≈ 0.87
    instead of 0.5), so using the white correlation for it over-counts long-τ evidence.
    """
    Q2, N2, _B2, K2, _R2 = (float(v) for v in coef)
    a, b, c = N2 * rate_hz, K2 / rate_hz, Q2 * rate_hz**2
    if not (a > 0 or b > 0 or c > 0):
        a, b, c = 1.0, 0.0, 0.0
    key = (tuple(int(v) for v in m), int(n_phase))
    T = _QF_STACK.get(key)
    if T is None:
        M = len(m)
        T = np.zeros((M, M, 6))
        for i in range(M):
            for j in range(i, M):
                mi, mj = int(m[i]), int(m[j])
                if max(mi, mj) > _MAX_RATIO * min(mi, mj):
                    continue
                T[i, j] = T[j, i] = _pair_quadratic(mi, mj, int(n_phase))
        _QF_STACK[key] = T
    C = T @ np.array([a * a, b * b, c * c, 2 * a * b, 2 * a * c, 2 * b * c])
    d = np.sqrt(np.diag(C))
    R = C / np.outer(d, d)
    # far pairs set to 0 may leave R slightly indefinite: clip its eigenvalues
    w, V = np.linalg.eigh(R)
    if w.min() < 1e-6:
        R = (V * np.maximum(w, 1e-6)) @ V.T
        d = np.sqrt(np.diag(R))
        R = R / np.outer(d, d)
    return R


@dataclass(frozen=True)
class _Fit:
    coef: np.ndarray  # (5,) c = (Q², N², B², K², R²)
    cov: np.ndarray  # (5, 5)
    edf: np.ndarray  # (M,)
    alpha: np.ndarray  # (M,)
    chi2: float = float("nan")  # whitened residual sum of squares at the final weights


def fit_ieee952(
    taus_s: np.ndarray,
    avar: np.ndarray,
    m: np.ndarray,
    n_phase: int,
    *,
    iterations: int = 4,
    terms: Sequence[str] = IEEE_TERMS,
) -> _Fit:
    """Joint non-negative generalised least-squares fit of the IEEE 952 terms.

    Model: σ²(τ) = A(τ)·c with c = (Q², N², B², K², R²) ≥ 0 (IEEE Std 952 eq. C.2 sum).
    Covariance of the AVAR estimates: C_ij = ρ_ij·√(V_i V_j), with V_i = 2σ_i⁴/edf_i
    (chi-square, NIST SP 1065 eq. 45), σ_i² from the current *model* (not the noisy estimate,
    which would bias the fit low), edf_i from Greenhall's algorithm for the noise type that
    dominates the model at τ_i, and ρ_ij the correlation between overlapping AVAR estimates
    under the current model's white, random-walk and quantization parts
    (:func:`avar_correlation_model`; white noise at the start). The system is whitened with the Cholesky
    factor of C and solved by NNLS; iterated ``iterations`` times from a white-noise start.

    Returns the coefficients and their covariance (AᵀC⁻¹A)⁻¹ at the final weights, computed
    without the sign constraint so that a term pinned at zero still gets an upper bound.
    """
    A_full = ieee952_design(taus_s)
    use = np.array([k in terms for k in IEEE_TERMS])
    A = A_full[:, use]
    m = np.asarray(m, dtype=np.int64)
    avar = np.asarray(avar, float)
    rate_hz = float(m[0] / taus_s[0])
    alpha = np.zeros(len(taus_s), dtype=int)
    model = avar.copy()
    coef = np.zeros(5)
    tiny = np.finfo(float).tiny

    def whitened(model_, alpha_):
        R = avar_correlation_model(m, n_phase, rate_hz, coef)
        edf_ = np.array([AV.power_law_edf(int(a_), int(mm), int(n_phase)) for a_, mm in zip(alpha_, m)])
        sd = np.sqrt(2.0 / edf_) * np.maximum(model_, tiny)
        L = np.linalg.cholesky(R * np.outer(sd, sd))
        # np.linalg.solve rather than scipy's solve_triangular: on these ~20×5 systems the
        # latter costs milliseconds per call (BLAS thread start-up), ×100 in the selection.
        W_ = np.linalg.solve(L, np.column_stack([A, avar]))
        Aw_, yw_ = W_[:, :-1], W_[:, -1]
        return edf_, Aw_, yw_

    for _ in range(max(1, iterations)):
        edf, Aw, yw = whitened(model, alpha)
        # Column scaling keeps NNLS well conditioned (the columns span many decades).
        scale = np.linalg.norm(Aw, axis=0)
        scale[scale == 0] = 1.0
        sol, _ = scipy.optimize.nnls(Aw / scale, yw, maxiter=50 * A.shape[1])
        coef = np.zeros(5)
        coef[use] = sol / scale
        new_model = A_full @ coef
        model = np.where(new_model > 0, new_model, avar)
        contrib = A_full * coef[None, :]
        alpha = np.array(_TERM_ALPHA)[np.argmax(contrib, axis=1)]
    edf, Aw, yw = whitened(model, alpha)
    chi2 = float(np.sum((yw - Aw @ coef[use]) ** 2))
    scale = np.linalg.norm(Aw, axis=0)
    scale[scale == 0] = 1.0
    An = Aw / scale
    cov_used = np.linalg.pinv(An.T @ An) / np.outer(scale, scale)
    cov = np.full((5, 5), np.nan)
    idx = np.flatnonzero(use)
    cov[np.ix_(idx, idx)] = cov_used
    return _Fit(coef=coef, cov=cov, edf=edf, alpha=alpha, chi2=chi2)


def term_interval(fit: _Fit, i: int) -> tuple[float, float, float]:
    """(c, lo, hi) of coefficient i with its 95 % normal interval on the variance scale."""
    c = float(fit.coef[i])
    v = fit.cov[i, i]
    se = math.sqrt(v) if (math.isfinite(v) and v > 0) else float("inf")
    return c, c - _Z95 * se, c + _Z95 * se


def select_ieee952(
    taus_s: np.ndarray, avar: np.ndarray, m: np.ndarray, n_phase: int, *, keep_z: float = 3.0
) -> tuple[_Fit, list[str], dict[str, float]]:
    """Joint fit with backward elimination of the terms the data cannot resolve.

    Start from all five terms; while some active term is not significant (c/se < ``keep_z``
    on the variance coefficient, or NNLS pinned it at 0), drop the least significant one
    (smallest c/se) and refit the others jointly; then add back the dropped term that, fitted next
    to the kept ones, lowers the generalised χ² most and is significant itself (if above ``keep_z`` without making a kept term
    insignificant) and repeat. ``keep_z = 3`` rather than 1.96: with four
    candidate terms absent, a 5 % level keeps a spurious one in ~20 % of white-noise records
    and the N interval then under-covers (measured 91 % for a nominal 95 %). Collinear neighbours (e.g. K and R, or B
    and K over a short τ range) would otherwise share one signal and all look insignificant.

    Returns the final fit, the active terms and, for each dropped term, an upper bound: the
    upper end of its 95 % interval when it replaces the kept terms of its τ family (B, K, R
    stand in for each other over a short record), or next to the final terms if larger.
    """

    def z_of(fit_: _Fit, name: str) -> float:
        c, _lo, hi = term_interval(fit_, IEEE_TERMS.index(name))
        se = (hi - c) / _Z95
        return c / se if (c > 0 and se > 0 and math.isfinite(se)) else 0.0

    active = list(IEEE_TERMS)
    upper: dict[str, float] = {}
    for _round in range(2 * len(IEEE_TERMS)):
        # backward: drop the least significant term while one is below keep_z
        while True:
            fit = fit_ieee952(taus_s, avar, m, n_phase, terms=active)
            zs = {name: z_of(fit, name) for name in active}
            worst = min(zs, key=zs.get)
            if zs[worst] >= keep_z or len(active) == 1:
                break
            upper[worst] = term_interval(fit, IEEE_TERMS.index(worst))[2]
            active.remove(worst)
        # forward: a dropped term that is significant next to the kept ones comes back
        # (collinear neighbours dropped together in the backward pass, e.g. B, K and R)
        best, best_chi2, best_hi = None, float("inf"), {}
        for name in IEEE_TERMS:
            if name in active:
                continue
            trial = fit_ieee952(taus_s, avar, m, n_phase, terms=active + [name])
            z = z_of(trial, name)
            best_hi[name] = term_interval(trial, IEEE_TERMS.index(name))[2]
            if z > keep_z and all(z_of(trial, k) >= keep_z for k in active) and trial.chi2 < best_chi2:
                best, best_chi2 = name, trial.chi2
        if best is None:
            # Upper bound of each dropped term: fitted in place of the kept terms of its own
            # τ family (long: B, K, R, which can stand in for each other over a short record;
            # short: Q), so that a neighbour does not absorb its signal.
            for name in IEEE_TERMS:
                if name in active:
                    continue
                if name in _LONG_TERMS:
                    trial_terms = [k for k in active if k not in _LONG_TERMS] + [name]
                else:
                    trial_terms = active + [name]
                trial = fit_ieee952(taus_s, avar, m, n_phase, terms=trial_terms)
                upper[name] = max(term_interval(trial, IEEE_TERMS.index(name))[2], best_hi.get(name, 0.0))
            return fit, active, upper
        active = [k for k in IEEE_TERMS if k in active or k == best]
        upper.pop(best, None)
    return fit, active, upper
