"""The bias-step test of the open search (:mod:`gyrocore.loop.search`, DESIGN.md "Effects outside the
catalogue").

A change-point test on the window residual. For each candidate time τ a local three-axis
contrast (h windows after minus h before) is projected off the model and its score tested (χ²₃ pointwise with the residual's
autocovariance model); the supremum over τ is calibrated by a parametric bootstrap from a
noise model identified on a robust structure function (:func:`step_noise_model`: white +
random walk + Gauss–Markov grid; a step moves few increments, wander moves all), because
random-walk and flicker bias noise make the naive CUSUM/χ² supremum false-alarm. Step vs
ramp is a model comparison: the blocked out-of-sample RMS of model + step vs model +
``bias_ramp``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gyrocore.calib.covariance import autocov_apply, residual_autocov_models

from .projection import project_off, weighted_design, weighted_residual

__all__ = ["screen_step", "simulate_gaussian", "step_noise_model", "simulate_noise_model", "StepScreen"]


def simulate_gaussian(g: np.ndarray, n: int, size: int, rng: np.random.Generator) -> np.ndarray:
    """Stationary Gaussian series with autocovariance g (lags 0..), shape (n, size).

    Circulant embedding (Dietrich & Newsam 1997): the autocovariance is embedded in a circulant
    of length 2n whose eigenvalues (FFT) give the spectrum; negative eigenvalues (a truncated
    model need not embed exactly) are set to 0.
    """
    c = np.zeros(n)
    L = min(g.size, n)
    c[:L] = g[:L]
    row = np.concatenate([c, [0.0], c[:0:-1]])  # length 2n
    lam = np.clip(np.fft.rfft(row).real, 0.0, None)
    m = row.size
    Z = rng.standard_normal((lam.size, size)) + 1j * rng.standard_normal((lam.size, size))
    Z[0] = Z[0].real * np.sqrt(2)
    if m % 2 == 0:
        Z[-1] = Z[-1].real * np.sqrt(2)
    y = np.fft.irfft(np.sqrt(lam / 2)[:, None] * Z, n=m, axis=0) * np.sqrt(m)
    return y[:n]


#: Correlation times (in windows) of the Gauss–Markov basis of :func:`step_noise_model`; a sum
#: of first-order Gauss–Markov terms over a geometric grid of τ approximates flicker noise.
_GM_TAUS = (1.0, 3.0, 10.0, 30.0, 100.0, 300.0, 1000.0)


def step_noise_model(x: np.ndarray) -> dict:
    """White + random walk + Gauss–Markov terms fitted to a robust structure function of x (M,).

    D(L) = median_t (x_{t+L} − x_t)² / 0.45494 (the median of χ²₁: unbiased for Gaussian
    increments) for L = 1, 2, 4, … ≤ M/16, fitted by non-negative least squares (relative
    errors) with D(L) = 2σ² + q·L + Σ_k 2s_k²(1 − φ_k^L), φ_k = exp(−1/τ_k) (:data:`_GM_TAUS`).
    A bias step moves only the L of M − L increments that straddle it (≤ 1/15 here), so the
    median hardly sees it, whereas random walk and flicker move every increment. Beyond M/16
    the fitted random-walk term extrapolates flicker's log growth linearly (conservative).
    """
    from scipy.optimize import nnls

    x = np.asarray(x, float)
    M = x.shape[0]
    Ls = []
    L = 1
    while L <= max(1, M // 16):
        Ls.append(L)
        L *= 2
    Ls = np.asarray(Ls)
    D = np.array([np.median((x[l:] - x[:-l]) ** 2) / 0.45494 for l in Ls])
    taus = np.asarray([t for t in _GM_TAUS if t <= 4 * M])
    phis = np.exp(-1.0 / taus)
    B = np.column_stack([np.full(Ls.size, 2.0), Ls.astype(float)] + [2 * (1 - ph**Ls) for ph in phis])
    w = 1.0 / np.maximum(D, 1e-300)
    coef, _ = nnls(B * w[:, None], D * w)
    return {"white_var": float(coef[0]), "rw_var": float(coef[1]), "gm_var": coef[2:], "gm_phi": phis}


def simulate_noise_model(model: dict, n: int, size: int, rng: np.random.Generator) -> np.ndarray:
    """Draws (n, size) of a :func:`step_noise_model` (white + random walk + Gauss–Markov), mean
    removed (the model under test has a bias)."""
    lag = np.arange(n)
    g = np.zeros(n)
    g[0] = model["white_var"]
    for v, ph in zip(model["gm_var"], model["gm_phi"]):
        if v > 0:
            g += v * ph**lag
    x = simulate_gaussian(g, n, size, rng) if g.any() else np.zeros((n, size))
    if model["rw_var"] > 0:
        x = x + np.cumsum(rng.standard_normal((n, size)) * np.sqrt(model["rw_var"]), axis=0)
    return x - x.mean(axis=0)


@dataclass(frozen=True, eq=False)
class StepScreen:
    index: int  # first window after the step
    t_s: float  # step time (start of that window), s
    statistic: float  # sup_τ χ²₃ statistic
    p_value: float  # bootstrap p-value of the supremum
    log10_p: float
    n_boot: int
    n_candidates: int
    size_rad_s: np.ndarray  # (3,) score estimate of the step

    def evidence(self) -> dict:
        """The scan's figures in a step's evidence (JSON keys of the loop's result)."""
        return {
            "sup_statistic": self.statistic,
            "bootstrap_p": self.p_value,
            "n_boot": self.n_boot,
            "n_candidates": self.n_candidates,
        }


def step_columns(res, idx: np.ndarray) -> np.ndarray:
    """Window regressors of unit bias steps starting at window ``idx`` (step at its start time):
    (M, 3, 3·J), column 3j + i on axis i (windows wholly after: 1, before: 0; exact at a
    window boundary)."""
    M = res.m
    J = idx.size
    C = np.zeros((M, 3, 3 * J))
    t0 = res.inputs.t_s[res.win_start]
    ts = t0[idx]
    for j in range(J):
        g = (t0 >= ts[j]).astype(float)
        for i in range(3):
            C[:, i, 3 * j + i] = g
    if res.R_GS is not None:
        # a constant vector held over a rotating window: apply the operator exactly
        for j in range(J):
            t = np.asarray(res.inputs.t_s, float)
            s = (t >= ts[j]).astype(float)
            A = np.zeros((t.size, 3, 3))
            for i in range(3):
                A[:, i, i] = s
            C[:, :, 3 * j : 3 * j + 3] = res.window_mean(A)
    return C


def _weighted_step_columns(res, idx: np.ndarray, sw: np.ndarray) -> np.ndarray:
    """``weighted_design(step_columns(res, idx), sw)`` built directly as (3M, 3J) (without the
    rotation operator: the same numbers, one array instead of two)."""
    if res.R_GS is not None:
        return weighted_design(step_columns(res, idx), sw)
    M, J = res.m, idx.size
    t0 = res.inputs.t_s[res.win_start]
    ts = t0[idx]
    Cw = np.zeros((3 * M, 3 * J))
    for j in range(J):
        g = (t0 >= ts[j]).astype(float)
        for i in range(3):
            Cw[i * M : (i + 1) * M, 3 * j + i] = g * sw[i]
    return Cw


#: Residual the step test's noise model is identified on: "alternative" (the residual with the
#: best step removed, as the catalogue's Wald tests use the alternative's residual) or "null"
#: (the model without a step: conservative, but a real step then inflates the low-frequency
#: part of the noise model so much that a 4σ step in 40 s goes undetected — measured).
STEP_NOISE_FROM = "alternative"


def _step_scores(Cp: np.ndarray, ew: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The scores z = Cpᵀ·ew (J, 3) and the Gram matrices (J, 3, 3) of the three weighted,
    projected step columns of each of the J candidate times (Cp (3M, 3J), column 3j + axis)."""
    J = Cp.shape[1] // 3
    z = (Cp.T @ ew).reshape(J, 3)
    Cp3 = Cp.reshape(Cp.shape[0], J, 3)
    return z, np.einsum("rja,rjb->jab", Cp3, Cp3)


def _refine_step(res, X0, e, sw, idx, jbest) -> int:
    """Window index of the least-squares step location between the coarse neighbours of
    ``idx[jbest]`` (the test ran on a thinned grid; the location is refined on every window)."""
    lo = int(idx[max(jbest - 1, 0)])
    hi = int(idx[min(jbest + 1, idx.size - 1)])
    fine = np.arange(lo, hi + 1)
    if fine.size <= 1:
        return int(idx[jbest])
    C = step_columns(res, fine)
    Cp = project_off(weighted_design(X0, sw), weighted_design(C, sw))
    z, G = _step_scores(Cp, weighted_residual(e, sw))
    gain = [float(z[j] @ np.linalg.lstsq(G[j], z[j], rcond=None)[0]) for j in range(fine.size)]
    return int(fine[int(np.argmax(gain))])


def screen_step(
    res,
    X0: np.ndarray,
    e: np.ndarray,
    sigma: np.ndarray,
    *,
    threshold: float,
    rng: np.random.Generator,
    max_candidates: int = 300,
    edge: int | None = None,
    max_boot: int = 4000,
    noise_from: str = STEP_NOISE_FROM,
) -> StepScreen | None:
    """Change-point test for a bias step (all three axes) on the window residual.

    Statistic: T(τ) = zᵀV⁻¹z with z the scores of the three *local contrast* columns (mean of
    the h = M/20 windows after τ minus the h before, per axis) projected off the model, V their
    covariance under the HAC autocovariance model of the residual with the best (full) step
    removed; sup over the candidate τ (every window start, thinned to ``max_candidates``, at
    least h windows from each end). The supremum's null distribution comes from a parametric
    bootstrap of the noise model of :func:`step_noise_model` (robust structure function:
    white + random walk + Gauss–Markov grid; :func:`simulate_noise_model`), B = ⌈2/threshold⌉
    draws (at least 199, at most ``max_boot``; so that the smallest attainable p-value,
    1/(B+1), is below the threshold), stopped once 20 draws exceed (Besag & Clifford 1991);
    p = (1 + #{T*_sup ≥ T_sup})/(B + 1). The location is refined to the window by least squares
    on the full step; ``size_rad_s`` is the full step's estimate there.
    """
    M = res.m
    edge = max(5, int(0.02 * M)) if edge is None else edge
    if M < 2 * edge + 10:
        return None
    # window boundaries that are contiguous in time (a step at a gap is a step between runs)
    h = max(8, M // 20)  # half-width of the local contrast, windows
    edge = max(edge, h)
    if M < 2 * edge + 10:
        return None
    idx = np.arange(edge, M - edge)
    if idx.size > max_candidates:
        idx = idx[np.linspace(0, idx.size - 1, max_candidates).astype(int)]
    sw = 1.0 / np.maximum(np.asarray(sigma, float), 1e-300)
    Xw = weighted_design(X0, sw)
    Cp = project_off(Xw, _weighted_step_columns(res, idx, sw), overwrite=True)
    ew = weighted_residual(e, sw)
    J = idx.size
    z, Gjj = _step_scores(Cp, ew)
    # best step by least squares (white weights) -> the alternative's residual -> noise model
    with np.errstate(invalid="ignore"):
        th = np.linalg.solve(Gjj + 1e-300 * np.eye(3), z[:, :, None])[:, :, 0]
    gain = np.einsum("ji,ji->j", z, th)
    jb = int(np.nanargmax(gain))
    e_alt = ew - Cp[:, 3 * jb : 3 * jb + 3] @ th[jb]
    # the full-step scores z (= Cpᵀ·ew) are all that is needed of Cp below (the size
    # estimate): Cp is released before the contrast columns are built (memory)
    zf = z.copy()
    del Cp
    E_alt = e_alt.reshape(3, M).T
    gs = residual_autocov_models(E_alt if noise_from == "alternative" else ew.reshape(3, M).T)
    # the test statistic is a *local* contrast (mean of the h windows after τ minus the h
    # before, projected off the model): abrupt changes count, slow wander (Gauss–Markov with a
    # correlation time of the record's length, flicker, random walk) hardly does — whereas the
    # global CUSUM contrast cannot tell a step from a wander that the short-lag noise model
    # does not see
    # the weighted contrast columns (weighted_design of the (M, 3, 3J) design: rows axis-major, axis
    # i's rows × √w_i), built in place: the same numbers, one (3M, 3J) array
    Clw = np.zeros((3 * M, 3 * J))
    for i in range(3):
        up, down = (1.0 / h) * sw[i], (-1.0 / h) * sw[i]
        for j, k in enumerate(idx):
            Clw[i * M + k : i * M + k + h, 3 * j + i] = up
            Clw[i * M + k - h : i * M + k, 3 * j + i] = down
    Clp = project_off(Xw, Clw, overwrite=True)
    del Clw
    z = (Clp.T @ ew).reshape(J, 3)
    V = np.zeros((J, 3, 3))
    for a in range(3):
        U = Clp[a * M : (a + 1) * M]
        GU = autocov_apply(U, gs[a])
        V += np.einsum("mja,mjb->jab", U.reshape(M, J, 3), GU.reshape(M, J, 3))
        del GU
    Vinv = np.linalg.pinv(V)
    Tobs = np.einsum("ji,jik,jk->j", z, Vinv, z)
    # null distribution: the noise model is identified on the residual *without* a step by a
    # robust structure function (step_noise_model): a step moves only the few increments that
    # straddle it, while random walk and flicker move them all. (The levels' own
    # autocovariance model either absorbs a real step — no power — or, fitted after removing
    # the best step, under-represents random-walk wander: 3 false alarms in 35 nulls, measured.)
    models = [step_noise_model(ew[a * M : (a + 1) * M]) for a in range(3)]
    jbest = int(np.argmax(Tobs))
    Tsup = float(Tobs[jbest])
    j_fine = _refine_step(res, X0, e, sw, idx, jbest)
    B = int(min(max(199, np.ceil(2.0 / max(threshold, 1e-12))), max_boot))
    exceed = 0
    done = 0
    chunk = 200
    CpT = Clp.T
    while done < B:
        b = min(chunk, B - done)
        Es = np.concatenate([simulate_noise_model(models[a], M, b, rng) for a in range(3)], axis=0)  # (3M, b)
        Zs = (CpT @ Es).reshape(J, 3, b)
        Ts = np.sum(Zs * np.matmul(Vinv, Zs), axis=1).max(axis=0)
        exceed += int(np.sum(Ts >= Tsup))
        done += b
        # sequential Monte Carlo (Besag & Clifford 1991): stop once the p-value is clearly large
        if exceed >= 20:
            break
    p = (1 + exceed) / (done + 1)
    # weighted columns against the weighted residual: the coefficient is the step in rad/s
    size = np.linalg.lstsq(Gjj[jbest], zf[jbest], rcond=None)[0]
    t_step = float(res.inputs.t_s[res.win_start[j_fine]])
    return StepScreen(
        index=int(j_fine),
        t_s=t_step,
        statistic=Tsup,
        p_value=float(p),
        log10_p=float(np.log10(p)),
        n_boot=done,
        n_candidates=J,
        size_rad_s=size,
    )
