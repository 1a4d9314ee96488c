"""Covariances of least-squares parameters: whiteness tests and the sandwich estimators.

The estimators behind :func:`gyrocore.calib.lsq.solve`'s ``covariance`` option (see that
module's docstring for when each is right):

* ``"ols"`` — s²·(AᵀWA)⁻¹;
* ``"hac"`` — the sandwich with the Toeplitz autocovariance of each axis' residual: sample
  values at short lags plus a fitted exponential (Gauss–Markov) tail
  (:func:`residual_autocov_model`, :func:`residual_sandwich_meat`);
* ``"newey_west"`` — Bartlett kernel on the score series, AR(1) pre-whitened, Andrews' plug-in
  bandwidth (:func:`long_run_covariance`);
* ``"block"`` — batch means over contiguous blocks;
* ``"noise_model"`` — the row covariance implied by the gyro's noise model
  (:func:`noise_model_meat`).

:func:`ljung_box_p` and :func:`low_frequency_excess` are the tests ``"auto"`` uses to choose
between ``"ols"`` and ``"hac"``.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

__all__ = [
    "ljung_box_p",
    "low_frequency_excess",
    "residual_autocov_model",
    "residual_autocov_models",
    "autocov_apply",
    "residual_sandwich_meat",
    "long_run_covariance",
    "noise_model_meat",
    "parameter_covariance",
]


def ljung_box_p(e: np.ndarray, *, n_lags: int | None = None) -> float:
    """Ljung–Box whiteness test, pooled over columns.

    Parameters
    ----------
    e : ndarray, shape (N,) or (N, k)
        Residual series (each column tested, Q statistics summed; they are independent under
        the null of white, mutually uncorrelated columns).
    n_lags : int, optional
        Lags tested, default min(20, N // 5).

    Returns
    -------
    float
        p-value of Q = N(N+2)·Σ_l ρ_l²/(N−l) against χ² with k·n_lags degrees of freedom.
    """
    e = np.asarray(e, float)
    if e.ndim == 1:
        e = e[:, None]
    n = e.shape[0]
    m = int(n_lags or min(20, n // 5))
    if m < 1:
        return float("nan")
    q = 0.0
    dof = 0
    for c in range(e.shape[1]):
        ac = _autocov(e[:, c], m)
        if ac[0] <= 0:
            continue
        rho = ac[1:] / ac[0]
        q += n * (n + 2) * float(np.sum(rho**2 / (n - np.arange(1, m + 1))))
        dof += m
    if dof == 0:
        return float("nan")
    return float(stats.chi2.sf(q, dof))


def _bartlett_obm(g: np.ndarray, L: int) -> np.ndarray:
    """Σ_l (1 − |l|/(L+1))·Γ_l via overlapping batch means (moving sums of L+1 scores).

    Equals the Bartlett-kernel long-run covariance up to edge terms; corrected by N/(N−L).
    g : (N, P). Cost O(N·P²).
    """
    n = g.shape[0]
    L = int(max(0, min(L, n - 2)))
    if L == 0:
        return g.T @ g
    cs = np.vstack([np.zeros((1, g.shape[1])), np.cumsum(g, axis=0)])
    G = cs[L + 1 :] - cs[: -(L + 1)]  # (N − L, P) moving sums
    return (G.T @ G) / (L + 1) * (n / (n - L))


def long_run_covariance(
    g: np.ndarray, *, prewhiten: bool = True, bandwidth: float | None = None
) -> tuple[np.ndarray, float]:
    """Long-run covariance Σ_l Γ_l of a (mean-zero) score series (Newey–West, Bartlett).

    Parameters
    ----------
    g : ndarray, shape (N, P)
        Score series g_n = Σ_i A[n,i,:]·w[n,i]·e[n,i].
    prewhiten : bool
        AR(1) pre-whitening per component (Andrews & Monahan 1992), AR coefficient clipped to
        [−0.97, 0.97]; the estimate is recoloured with (1 − φ)⁻¹.
    bandwidth : float, optional
        Bartlett bandwidth in samples; default: Andrews (1991) AR(1) plug-in,
        L = 1.1447·(α·N)^(1/3), α = Σ 4ρ²σ⁴/((1−ρ)⁶(1+ρ)²) / Σ σ⁴/(1−ρ)⁴.

    Returns
    -------
    S : ndarray, shape (P, P)
    L : float — the bandwidth used.
    """
    g = np.asarray(g, float)
    n, P = g.shape
    phi = np.zeros(P)
    if prewhiten and n > 10:
        num = np.einsum("np,np->p", g[1:], g[:-1])
        den = np.einsum("np,np->p", g[:-1], g[:-1])
        with np.errstate(invalid="ignore", divide="ignore"):
            phi = np.where(den > 0, num / den, 0.0)
        phi = np.clip(phi, -0.97, 0.97)
        gw = g[1:] - phi[None, :] * g[:-1]
    else:
        gw = g
    if bandwidth is None:
        x0, x1 = gw[:-1], gw[1:]
        num = np.einsum("np,np->p", x1, x0)
        den = np.einsum("np,np->p", x0, x0)
        ok = den > 0
        rho = np.zeros(P)
        rho[ok] = np.clip(num[ok] / den[ok], -0.97, 0.97)
        sig2 = np.zeros(P)
        sig2[ok] = np.mean((x1 - rho * x0)[:, ok] ** 2, axis=0)
        a_num = np.sum(4 * rho**2 * sig2**2 / ((1 - rho) ** 6 * (1 + rho) ** 2))
        a_den = np.sum(sig2**2 / (1 - rho) ** 4)
        alpha = a_num / a_den if a_den > 0 else 0.0
        bandwidth = 1.1447 * (alpha * gw.shape[0]) ** (1.0 / 3.0)
        bandwidth = float(min(bandwidth, gw.shape[0] / 4))
    S = _bartlett_obm(gw, int(np.ceil(bandwidth)))
    S *= n / max(gw.shape[0], 1)
    if prewhiten:
        D = 1.0 / (1.0 - phi)
        S = D[:, None] * S * D[None, :]
    return S, float(bandwidth)


def _autocov(x: np.ndarray, m: int) -> np.ndarray:
    """Biased sample autocovariance γ̂(0..m) of a 1-D series (FFT), mean removed."""
    n = x.shape[0]
    x = x - x.mean()
    nf = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfft(x, nf)
    return np.fft.irfft(f * np.conj(f), nf)[: m + 1] / n


def _short_and_tail(x: np.ndarray, n_direct: int, max_lag: int | None, tail_floor: float) -> np.ndarray:
    """Sample autocovariance at lags ≤ n_direct plus a fitted exponential tail (see below)."""
    n = x.shape[0]
    m = int(max_lag or max(n_direct + 1, min(n // 10, 5000)))
    m = min(m, n - 1)
    ac = _autocov(x, m)
    g = ac[: n_direct + 1].copy()
    if ac[0] <= 0 or m <= n_direct + 3:
        return g
    c = ac[n_direct + 1 :]
    sig = c > 2.0 * ac[0] / np.sqrt(n)
    if not sig[0]:
        return g
    end = int(np.argmin(sig)) if not sig.all() else sig.size
    if end < 3:
        return g
    lags = np.arange(n_direct + 1, n_direct + 1 + end)
    slope, icpt = np.polyfit(lags, np.log(c[:end]), 1)
    phi = float(np.exp(slope))
    if not 0 < phi < 1:
        phi = min(max(phi, 1e-6), 0.99999)
    Lcut = int(min(np.ceil(np.log(tail_floor) / np.log(phi)), n - 1))
    if Lcut <= n_direct:
        return g
    tail = np.exp(icpt) * phi ** np.arange(n_direct + 1, Lcut + 1)
    return np.concatenate([g, tail])


def _block_mean_var_model(g: np.ndarray, L: int) -> float:
    """Var of the mean of L consecutive samples under autocovariance g (zero beyond its end)."""
    k = min(L, g.size)
    l = np.arange(1, k)
    return float((L * g[0] + 2.0 * np.sum((L - l) * g[1:k])) / L**2)


def _block_mean_vars(x: np.ndarray, g: np.ndarray):
    """For L = 16, 32, … ≤ N/8: (L, m, the sample variance (ddof 1) of the m = N // L means of L
    consecutive samples of x − mean(x), its model :func:`_block_mean_var_model` under g); lazily
    (a test may stop at the first block length that says enough)."""
    n = x.shape[0]
    xc = x - x.mean()
    L = 16
    while L <= n // 8:
        m = n // L
        bm = xc[: m * L].reshape(m, L).mean(axis=1)
        yield L, m, float(np.var(bm, ddof=1)), _block_mean_var_model(g, L)
        L *= 2


def _gm_block_var(s2: float, phi: float, L: int) -> float:
    """Var of an L-sample mean of a Gauss–Markov sequence (variance s2, lag-1 corr φ)."""
    if phi <= 0:
        return s2 / L
    return float(s2 / L**2 * (L * (1 + phi) / (1 - phi) - 2 * phi * (1 - phi**L) / (1 - phi) ** 2))


def low_frequency_excess(x: np.ndarray, *, alpha: float = 1e-3, n_direct: int = 5) -> bool:
    """True when block means of ``x`` vary more than its short-lag autocovariance explains
    (χ² test at level ``alpha`` for L = 16, 32, … ≤ N/8): slow noise such as bias instability
    that a lag-by-lag whiteness test (Ljung–Box) does not see."""
    x = np.asarray(x, float)
    n = x.shape[0]
    if n < 16 * 8:
        return False
    g = _autocov(x, n_direct)
    for L, m, v, v_model in _block_mean_vars(x, g):
        if v > stats.chi2.ppf(1 - alpha, m - 1) / (m - 1) * v_model:
            return True
    return False


def residual_autocov_model(
    x: np.ndarray,
    *,
    n_direct: int = 5,
    max_lag: int | None = None,
    tail_floor: float = 1e-4,
    low_freq_check: bool = True,
    alpha: float = 1e-3,
) -> np.ndarray:
    """Autocovariance model of a stationary residual: sample values, an exponential tail, and
    a slow component when block means say there is more low-frequency power.

    1. γ(l) = γ̂(l) for l ≤ ``n_direct`` (the short, well-estimated lags: white noise, on-chip
       low-pass).
    2. Beyond, γ(l) = a·φ^l fitted (log-linear least squares) to the run of sample lags that
       stand above 2·γ̂(0)/√N (the sd of a sample autocovariance of white noise) — the
       first-order Gauss–Markov part of gyro noise (DESIGN.md ``correlated``). Without such a
       run the tail is 0; it is cut where φ^l < ``tail_floor``.
    3. Flicker (bias-instability) noise has per-lag correlations too small to pass step 2
       and yet dominates the variance of long averages. So the variance of block means
       V(L) = Var(mean of L samples) is compared with the model's for L = 16, 32, … ≤ N/8;
       where V_obs/V_model exceeds the χ²_{m−1}(1 − α)/(m − 1) bound (m = N/L blocks), a
       second Gauss–Markov component s²·φ₂^l is added, φ₂ = exp(−1/L*) on the grid of L and
       s² by weighted least squares on the excess V_obs − V_model (weights m − 1), the best
       grid point kept. Its tail is cut at φ₂^l < ``tail_floor`` (at most N − 1 lags).

    Parameters
    ----------
    x : ndarray, shape (N,)
        Residual of one axis, rad/s.

    Returns
    -------
    ndarray, shape (L + 1,)
        γ(0..L), (rad/s)².
    """
    x = np.asarray(x, float)
    n = x.shape[0]
    g = _short_and_tail(x, n_direct, max_lag, tail_floor)
    if not low_freq_check or n < 16 * 8:
        return g
    Ls, vobs, vmod, wts = [], [], [], []
    for L, m, v, v_model in _block_mean_vars(x, g):
        Ls.append(L)
        vobs.append(v)
        vmod.append(v_model)
        wts.append(m - 1)
    if not Ls:
        return g
    Ls, vobs, vmod, wts = map(np.asarray, (Ls, vobs, vmod, wts))
    crit = stats.chi2.ppf(1 - alpha, wts) / wts
    if not np.any(vobs > crit * vmod):
        return g
    excess = np.clip(vobs - vmod, 0.0, None)
    best = None
    # candidate correlation times: the block lengths, and beyond them up to N/2 (flicker
    # noise keeps V(L) flat to the longest blocks: its correlation outlasts what they show)
    cands = list(Ls) + [int(Ls[-1] * 2), int(Ls[-1] * 4)]
    for Lstar in cands:
        phi2 = float(np.exp(-1.0 / Lstar))
        basis = np.array([_gm_block_var(1.0, phi2, int(L_)) for L_ in Ls])
        w = wts / np.maximum(vobs, 1e-300) ** 2  # relative (log-like) weighting
        s2 = float(np.sum(w * basis * excess) / np.sum(w * basis**2))
        if s2 <= 0:
            continue
        err = float(np.sum(w * (excess - s2 * basis) ** 2))
        if best is None or err < best[0]:
            best = (err, s2, phi2)
    if best is None:
        return g
    _, s2, phi2 = best
    Lcut = int(min(np.ceil(np.log(tail_floor) / np.log(phi2)), n - 1))
    out = np.zeros(max(g.size, Lcut + 1))
    out[: g.size] = g
    out[: Lcut + 1] += s2 * phi2 ** np.arange(Lcut + 1)
    return out


def residual_autocov_models(e: np.ndarray) -> list[np.ndarray]:
    """:func:`residual_autocov_model` of each column of e (N, K): K arrays γ(0..L)."""
    return [residual_autocov_model(e[:, i]) for i in range(e.shape[1])]


#: Columns per block of :func:`autocov_apply` (memory only: the complex spectra of all 900
#: columns of a step scan at once are ~0.3 GB; each column's convolution is independent).
AUTOCOV_BLOCK_COLUMNS = 64


def autocov_apply(U: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Γ·U for the Toeplitz autocovariance Γ of lags 0..L given by g (:func:`residual_autocov_model`),
    U (M, K): a convolution along time by FFT (scipy.signal.fftconvolve), lags beyond M − 1
    unused. Returns (M, K)."""
    from scipy import signal as _signal

    M = U.shape[0]
    L = min(g.size - 1, M - 1)
    if L <= 0:
        return g[0] * U
    ker = np.concatenate([g[L:0:-1], g[: L + 1]])  # lags −L..L
    K = U.shape[1]
    if K <= AUTOCOV_BLOCK_COLUMNS:
        return _signal.fftconvolve(U, ker[:, None], mode="full", axes=0)[L : L + M]
    out = np.empty(U.shape)
    for c in range(0, K, AUTOCOV_BLOCK_COLUMNS):
        out[:, c : c + AUTOCOV_BLOCK_COLUMNS] = _signal.fftconvolve(
            U[:, c : c + AUTOCOV_BLOCK_COLUMNS], ker[:, None], mode="full", axes=0
        )[L : L + M]
    return out


def residual_sandwich_meat(A: np.ndarray, W: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, int]:
    """Meat Σ_i (W_i A_i)ᵀ Γ_i (W_i A_i) of the sandwich covariance with stationary errors.

    Γ_i is the Toeplitz autocovariance of axis i's residual from
    :func:`residual_autocov_model` (axes assumed mutually uncorrelated); the product is a
    convolution along time, done by FFT (:func:`autocov_apply`), O(P·N log N).

    Parameters
    ----------
    A : ndarray, shape (N, 3, P)
    W : ndarray, shape (N, 3) — row weights
    e : ndarray, shape (N, 3) — residual, rad/s

    Returns
    -------
    S : ndarray, shape (P, P)
    L : int — the longest lag used.
    """
    n, _, P = A.shape
    S = np.zeros((P, P))
    Lmax = 0
    for i in range(3):
        g = residual_autocov_model(e[:, i])
        L = g.size - 1
        Lmax = max(Lmax, L)
        u = A[:, i, :] * W[:, i, None]
        cols = np.flatnonzero(np.any(u != 0, axis=0))
        if not cols.size:
            continue
        if L == 0:
            S[np.ix_(cols, cols)] += g[0] * (u[:, cols].T @ u[:, cols])
            continue
        S[np.ix_(cols, cols)] += u[:, cols].T @ autocov_apply(u[:, cols], g)  # L ≤ n − 1: every lag of g
    return (S + S.T) / 2, Lmax


#: Coarse bins (at most) over which the slow noise terms (flicker, random walk, Gauss–Markov)
#: of :func:`noise_model_meat` are integrated (dense K×K covariance).
NOISE_MODEL_BINS: int = 1500


def noise_model_meat(
    U: np.ndarray,
    row_t0_s: np.ndarray,
    row_t1_s: np.ndarray,
    row_n_eff: np.ndarray,
    noise,
    *,
    dt_s: float,
    max_bins: int = NOISE_MODEL_BINS,
) -> np.ndarray:
    """Meat Σ_i U_iᵀ·C_i·U_i of the sandwich covariance with C_i the covariance of the rows'
    noise *implied by a noise model* (white + flicker + rate random walk + Gauss–Markov).

    Each row of the fit is a (weighted) mean of samples over [t0, t1); its noise is the mean
    of the gyro noise there. Per axis i (axes independent):

    * white N_i (+ quantization LSB²/12 per sample): Var = (N_i²/dt + LSB²/12)/n_eff, rows
      uncorrelated — exact;
    * flicker B, random walk K, Gauss–Markov (σ, τc), started at the power-up (t = 0) as the
      chip and :mod:`sim.noise` do: the rows are grouped into at most ``max_bins`` contiguous
      time bins c; Σ_b U_b·x̄_b ≈ Σ_c V_c·x̄_c with V_c = Σ_{b∈c} U_b, and Cov(x̄_c, x̄_d) in
      closed form (:func:`gyrocore.calib.budget.block_covariance`, the same formulas as the drift
      prediction). Exact when every bin is one row; otherwise the error is the slow noise's
      variation inside a bin times the regressors' variation inside it (bins ≤ T/1500: a
      0.26-s bin for a 387-s table run, where the flicker's within-bin variance B² is ~1 % of
      a row's white variance and the regressors are piecewise constant).

    Parameters
    ----------
    U : ndarray, shape (n, 3, P)
        Weighted regressors of the fitted rows (A·W, W = row weight / axis σ²), SI.
    row_t0_s, row_t1_s : ndarray, shape (n,)
        Interval each row averages, s since the power-up (non-decreasing rows).
    row_n_eff : ndarray, shape (n,) or (n, 3)
        Effective number of samples of each row's mean, (Σw)²/Σw² (the count for 0/1 weights).
    noise : gyrocore.noise.model.NoiseModel
        Per-axis noise levels (:meth:`gyrocore.noise.allan.AllanAnalysis.noise_model` for an
        identified model).
    dt_s : float
        Sample spacing, s.
    max_bins : int

    Returns
    -------
    ndarray, shape (P, P)
    """
    from .budget import Blocks, block_covariance

    U = np.asarray(U, float)
    n, _, P = U.shape
    t0 = np.asarray(row_t0_s, float)
    t1 = np.asarray(row_t1_s, float)
    ne = np.broadcast_to(np.asarray(row_n_eff, float).reshape(n, -1), (n, 3))
    S = np.zeros((P, P))
    # -- white (ARW + quantization), per sample variance N²/dt + LSB²/12
    s2 = np.asarray(noise.arw_rad_per_sqrt_s, float) ** 2 / dt_s + float(noise.quantization_lsb_rad_s) ** 2 / 12.0
    for i in range(3):
        v = s2[i] / np.where(ne[:, i] > 0, ne[:, i], np.inf)
        S += U[:, i, :].T @ (U[:, i, :] * v[:, None])
    # -- slow terms on coarse time bins
    B2 = np.asarray(noise.bias_instability_rad_s, float) ** 2
    K2 = np.asarray(noise.rrw_rad_per_s_sqrt_s, float) ** 2
    gs = np.asarray(noise.correlated_sigma_rad_s, float)
    gt = np.asarray(noise.correlated_tau_c_s, float)
    if not (np.any(B2 > 0) or np.any(K2 > 0) or np.any(gs > 0)):
        return (S + S.T) / 2
    K = int(min(n, max(1, max_bins)))
    edges = np.linspace(0, n, K + 1).round().astype(int)
    edges = np.unique(edges)
    lo, hi = edges[:-1], edges[1:]
    V = np.add.reduceat(U, lo, axis=0)  # (K, 3, P)
    bt0, bt1 = t0[lo], t1[hi - 1]
    bt1 = np.maximum(bt1, bt0 + 1e-12)
    Kb = lo.size
    blk = Blocks(
        i0=lo, i1=hi, t0_s=bt0, t1_s=bt1, scored=np.ones(Kb, bool), segment=np.zeros(Kb, int), window=np.full(Kb, -1)
    )
    terms = []
    if np.any(B2 > 0):
        terms.append((block_covariance(blk, "bias_instability"), B2))
    if np.any(K2 > 0):
        terms.append((block_covariance(blk, "rrw"), K2))
    for i in range(3):
        if gs[i] > 0 and np.isfinite(gt[i]) and gt[i] > 0:
            L2 = np.zeros(3)
            L2[i] = gs[i] ** 2
            terms.append((block_covariance(blk, "correlated", tau_c_s=float(gt[i])), L2))
    for C, L2 in terms:
        for i in range(3):
            if L2[i] > 0:
                Vi = V[:, i, :]
                S += L2[i] * (Vi.T @ (C @ Vi))
    return (S + S.T) / 2


def parameter_covariance(
    kind: str, Ak, W, e, ew, bread, *, n: int, dof: int, rows_t, noise_model, dt_s: float, hac_bandwidth, n_blocks: int
) -> tuple[np.ndarray, float]:
    """Covariance of the kept parameters of the ``kind`` named in the module docstring, and the
    HAC bandwidth used (NaN where none)."""
    k = Ak.shape[2]
    L = float("nan")
    if kind == "ols":
        s2 = float(np.sum(ew**2)) / dof
        return s2 * bread, L
    if kind == "noise_model":
        meat = noise_model_meat(Ak * W[:, :, None], rows_t[0], rows_t[1], rows_t[2], noise_model, dt_s=dt_s)
        cov_k = bread @ meat @ bread
        return 0.5 * (cov_k + cov_k.T), L
    g = None if kind == "hac" else np.einsum("nip,ni->np", Ak, W * e)  # scores (n, k)
    if kind == "hac":
        S, L = residual_sandwich_meat(Ak, W, e)
        S *= n / max(n - k / 3.0, 1.0)  # dof: k parameters over 3 axes
    elif kind == "newey_west":
        S, L = long_run_covariance(g, bandwidth=hac_bandwidth)
    else:
        M = int(max(2, min(n_blocks, n // 2)))
        edges = np.linspace(0, n, M + 1).astype(int)
        Gb = np.stack([g[a:b].sum(axis=0) for a, b in zip(edges[:-1], edges[1:])])
        Gb = Gb - Gb.mean(axis=0)
        S = Gb.T @ Gb * (M / (M - 1))
    if kind != "hac":
        S *= (n * 3) / dof  # small-sample correction
    # a lag-truncated autocovariance sum need not be positive semidefinite; clip its
    # negative eigenvalues (projection onto the PSD cone) so no variance is negative
    S = 0.5 * (S + S.T)
    lam, V = np.linalg.eigh(S)
    if lam.min() < 0:
        S = (V * np.clip(lam, 0, None)) @ V.T
    return bread @ S @ bread, L
