"""Joint least squares over catalogue effects, with honest standard errors.

The measurement model of :mod:`gyrocore.effects.registry`, linearised at zero error, is

    r(t_n) = y(t_n) − ω_ref(t_n) ≈ A(t_n)·θ + e(t_n),       A from ``effects.design``

with ``r`` and ``e`` of shape (N, 3), ``A`` of shape (N, 3, P) and θ the stacked parameters of
the chosen effects. Per-axis effects (bias, scale, ...) are block-diagonal in A; a shared
parameter (``time_offset``) has one column that touches all three axes. The whole 3-axis
problem is solved at once, so cross-axis terms (misalignment, g-sensitivity) and shared terms
are estimated jointly.

Estimation is weighted least squares (axis weights 1/σ_i² from a first pass, times optional
user row weights). Standard errors come from one of three covariances:

* ``"ols"`` — s²·(AᵀWA)⁻¹, right when the residual is white;
* ``"hac"`` — the sandwich (AᵀWA)⁻¹·(AᵀW·Γ·WA)·(AᵀWA)⁻¹ with Γ the Toeplitz
  autocovariance of each axis' residual: sample values at short lags plus a fitted
  exponential (Gauss–Markov) tail (:func:`residual_autocov_model`). Right for coloured
  residuals (on-chip low-pass, Gauss–Markov bias, bias instability over the record), and
  honest even when the correlation time is long, where kernel estimators on the score
  (Newey–West) truncate the tail and understate the error (checked by Monte Carlo in
  tests/gyrocore/calib/test_lsq.py);
* ``"newey_west"`` — the Newey & West (1987) Bartlett-kernel sandwich on the score series,
  AR(1) pre-whitened with the Andrews (1991) plug-in bandwidth (Andrews & Monahan 1992);
* ``"block"`` — batch means over ``n_blocks`` contiguous blocks (cluster-robust by time).

``"auto"`` (the default) runs a Ljung–Box test on the weighted residual and a block-mean
variance test for slow noise (:func:`low_frequency_excess`) and uses ``"hac"`` when either
finds the residual coloured (p < 0.01 / α = 1e-3), ``"ols"`` otherwise; the result says which
(:attr:`LsqFit.cov_kind`) and the Ljung–Box p (:attr:`LsqFit.ljung_box_p`).

Observability: columns are checked in the declared effect order by a rank-revealing
(sequential Gram–Schmidt) test on the column-equilibrated matrix; a column whose part outside
the span of the earlier columns is below ``rank_rtol`` of its norm (a never-rotated axis, f
constant and so collinear with bias, ...) is *unobservable*: it is not fitted (its value is
reported as 0 with an infinite standard error) and it is named in
:attr:`LsqFit.unobservable` as ``"effect.param[index]"``. After the fit, a parameter whose
standard error exceeds its physically plausible magnitude (:data:`PLAUSIBLE_MAGNITUDE`) is
named as well — the data then say nothing that its plausible range did not already say — and
the fit is redone without it (``on_unobservable="drop"``) or :class:`UnobservableError` is
raised (``"raise"``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
from scipy import linalg, stats

from gyrocore.effects import registry as E
from gyrocore.errors import GyroInputError, UnobservableError

__all__ = [
    "LsqFit",
    "build_design",
    "solve",
    "fit_effects",
    "RowSource",
    "ArrayRows",
    "PLAUSIBLE_MAGNITUDE",
    "NOISY_REGRESSOR_EFFECTS",
    "ljung_box_p",
    "low_frequency_excess",
    "residual_autocov_model",
    "long_run_covariance",
    "noise_model_meat",
]

#: Largest physically plausible |θ| per effect, SI (used to call a parameter unobservable when
#: its standard error exceeds it). Generous on purpose: a consumer MEMS gyro is far inside.
PLAUSIBLE_MAGNITUDE: dict[str, float] = {
    # from the registry (gyrocore.effects.registry, Effect.plausible): bias 1 rad/s (57 deg/s),
    # bias_thermal 0.05 rad/s per °C^k, bias_temp_rate 1 rad/s per °C/s, bias_ramp 1e-2 rad/s²,
    # scale 0.5, scale_thermal 0.01 per °C^k, scale_asymmetry 0.2, scale_nonlinearity 0.2 s/rad,
    # misalignment 0.2 rad (11 deg), g_sensitivity 5e-3 rad/s per m/s² (2.8 deg/s/g),
    # g2_sensitivity 1e-3 rad/s per (m/s²)², time_offset 1 s. Family terms: periodic/step
    # 1 rad/s, regressor unbounded (its unit depends on the signal).
    e.name: e.plausible
    for e in E.REGISTRY.values()
    if e.fittable
}


#: Effects whose regressors are built from measured, noisy inputs (accel, temperature).
NOISY_REGRESSOR_EFFECTS: tuple[str, ...] = tuple(e.name for e in E.REGISTRY.values() if e.fittable and e.noisy)


def _plausible(plaus: Mapping[str, float], eff: str) -> float:
    if eff in plaus:
        return plaus[eff]
    try:
        return E.resolve(eff).plausible
    except GyroInputError:
        return np.inf


def _column_effect(name: str) -> str:
    """Effect of a column name ``"effect.param[index]"`` (a family name may hold a '.': periodic[37.5].a_cos_rad_s[0])."""
    if "[" in name.split(".", 1)[0]:
        return name[: name.index("]") + 1]
    return name.split(".", 1)[0]


def _is_noisy(eff: str, noisy_effects) -> bool:
    """A catalogue effect listed in ``noisy_effects``, or a family term built from accel/temperature."""
    return eff in noisy_effects or (E.is_family(eff) and E.resolve(eff).noisy)


@dataclass(frozen=True, eq=False)
class LsqFit:
    """Result of a joint least-squares fit.

    Attributes
    ----------
    theta : ndarray, shape (P,)
        Estimated parameters in SI, in column order; unobservable ones are 0.
    names : tuple of str, length P
        ``"effect.param[index]"`` per column (e.g. ``"scale.s[0]"``).
    slices : dict
        Effect name -> slice into ``theta`` of that effect's columns.
    cov : ndarray, shape (P, P)
        Covariance of ``theta`` (rows/columns of unobservable parameters are NaN off the
        diagonal, +inf on it).
    stderr : ndarray, shape (P,)
        sqrt(diag(cov)); +inf for unobservable parameters.
    cov_kind : str
        ``"ols"``, ``"hac"``, ``"newey_west"`` or ``"block"`` — which covariance ``cov`` is.
    ljung_box_p : float
        p-value of the Ljung–Box whiteness test on the weighted residual (small = coloured).
    hac_bandwidth : float
        Longest lag (samples after ``stride``) of the autocovariance used by ``"hac"`` or the
        Bartlett bandwidth of ``"newey_west"``; NaN otherwise.
    residual_rad_s : ndarray, shape (N, 3)
        r − A·θ on all N input samples (not only the strided ones), rad/s.
    residual_rms_rad_s : ndarray, shape (3,)
        RMS of the residual per axis over the rows used in the fit, rad/s.
    axis_sigma_rad_s : ndarray, shape (3,)
        Per-axis residual standard deviation used for the axis weights, rad/s.
    rank : int
        Number of fitted (observable) columns.
    condition : float
        2-norm condition number of the column-equilibrated, weighted design of the fitted
        columns.
    unobservable : tuple of str
        Names of parameters the data cannot determine (not fitted).
    unobservable_reason : dict
        Name -> one-line reason ("collinear with ...", "stderr ... > plausible ...").
    n_rows : int
        Rows used in the fit (after stride, zero-weight rows and block averaging).
    dof : int
        3·n_rows − rank.
    """

    theta: np.ndarray
    names: tuple[str, ...]
    slices: dict[str, slice]
    cov: np.ndarray
    stderr: np.ndarray
    cov_kind: str
    ljung_box_p: float
    hac_bandwidth: float
    residual_rad_s: np.ndarray
    residual_rms_rad_s: np.ndarray
    axis_sigma_rad_s: np.ndarray
    rank: int
    condition: float
    unobservable: tuple[str, ...]
    unobservable_reason: dict[str, str] = field(default_factory=dict)
    n_rows: int = 0
    dof: int = 0

    def effect_theta(self, effect: str) -> np.ndarray:
        """The flat parameter vector of one effect."""
        return self.theta[self.slices[effect]]

    def effect_stderr(self, effect: str) -> np.ndarray:
        """The flat standard errors of one effect."""
        return self.stderr[self.slices[effect]]

    def observable_mask(self) -> np.ndarray:
        """Boolean (P,): True for fitted columns."""
        bad = set(self.unobservable)
        return np.array([n not in bad for n in self.names])


# ---------------------------------------------------------------------------- design
def build_design(
    effects: Sequence[str],
    inp: E.ModelInputs,
    *,
    orders: Mapping[str, int] | None = None,
    t0_c: float | None = None,
) -> tuple[np.ndarray, list[str], dict[str, slice]]:
    """Stack the regressors of ``effects`` (in the given order).

    Parameters
    ----------
    effects : sequence of str
        Fittable catalogue effects (see :func:`gyrocore.effects.registry.design`).
    inp : ModelInputs
        Physical inputs; ``omega_S_rad_s`` is the reference rate (rad/s, S frame).
    orders : mapping, optional
        Polynomial order per thermal effect (``bias_thermal``, ``scale_thermal``); default 1.
    t0_c : float, optional
        T0 of the thermal polynomials, °C; default the mean of ``inp.temp_c`` (see
        :func:`gyrocore.effects.registry.design`).

    Returns
    -------
    A : ndarray, shape (N, 3, P)
    names : list of str, length P — ``"effect.param[index]"``
    slices : dict effect -> slice
    """
    orders = dict(orders or {})
    blocks, names, slices = [], [], {}
    p0 = 0
    for eff in E.check_effect_names(effects):
        if eff in slices:
            raise GyroInputError(f"effect {eff} listed twice")
        cn, A = E.design(eff, inp, order=int(orders.get(eff, 1)), t0_c=t0_c)
        blocks.append(A)
        names += [f"{eff}.{c}" for c in cn]
        slices[eff] = slice(p0, p0 + A.shape[2])
        p0 += A.shape[2]
    if not blocks:
        raise GyroInputError("no effects to fit")
    return np.concatenate(blocks, axis=2), names, slices


# ---------------------------------------------------------------------------- statistics
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
    xc = x - x.mean()
    L = 16
    while L <= n // 8:
        m = n // L
        bm = xc[: m * L].reshape(m, L).mean(axis=1)
        if np.var(bm, ddof=1) > stats.chi2.ppf(1 - alpha, m - 1) / (m - 1) * _block_mean_var_model(g, L):
            return True
        L *= 2
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
    xc = x - x.mean()
    Ls, vobs, vmod, wts = [], [], [], []
    L = 16
    while L <= n // 8:
        m = n // L
        bm = xc[: m * L].reshape(m, L).mean(axis=1)
        Ls.append(L)
        vobs.append(float(np.var(bm, ddof=1)))
        vmod.append(_block_mean_var_model(g, L))
        wts.append(m - 1)
        L *= 2
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


def residual_sandwich_meat(A: np.ndarray, W: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, int]:
    """Meat Σ_i (W_i A_i)ᵀ Γ_i (W_i A_i) of the sandwich covariance with stationary errors.

    Γ_i is the Toeplitz autocovariance of axis i's residual from
    :func:`residual_autocov_model` (axes assumed mutually uncorrelated); the product is a
    convolution along time, done by FFT (scipy.signal.fftconvolve), O(P·N log N).

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
    from scipy import signal as _signal

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
        ker = np.concatenate([g[::-1], g[1:]])  # lags −L..L
        v = _signal.fftconvolve(u[:, cols], ker[:, None], mode="full", axes=0)[L : L + n]
        S[np.ix_(cols, cols)] += u[:, cols].T @ v
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
    noise : gyrocore.calib.budget.NoiseModel
        Per-axis noise levels (:meth:`gyrocore.calib.budget.NoiseModel.from_identified` for an
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
    K2 = np.asarray(noise.rrw_rad_s_per_sqrt_s, float) ** 2
    gs = np.asarray(noise.gm_sigma_rad_s, float)
    gt = np.asarray(noise.gm_tau_c_s, float)
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


# ---------------------------------------------------------------------------- solver
def _flat(A: np.ndarray, w: np.ndarray) -> np.ndarray:
    """sqrt(w)-scaled design, (N·3, P)."""
    return (A * np.sqrt(w)[:, :, None]).reshape(-1, A.shape[2])


def _solve_pos(G: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve the symmetric positive (semi-)definite system G x = b.

    Exactly singular G (a candidate's columns collinear with the model's on this record, e.g. a
    companion term that repeats a kept column): SciPy ≥ 1.17 raises ``LinAlgError`` where older
    releases returned a solution with a ``LinAlgWarning``; the minimum-norm least-squares
    solution is then the same fit (the covariance uses ``pinvh`` in any case).
    """
    try:
        return linalg.solve(G, b, assume_a="pos")
    except linalg.LinAlgError:
        return linalg.lstsq(G, b)[0]


def _sequential_rank(G: np.ndarray, rtol: float) -> tuple[list[int], dict[int, tuple[int, ...]]]:
    """Columns kept in the given order by a rank-revealing sequential test (no pivoting, so
    the declared order decides which of two collinear columns is kept).

    Works on the Gram matrix G = XᵀX of the (weighted) design: with columns equilibrated to
    unit norm, the squared norm of column p's part outside the span of the kept columns is
    the Schur complement G_pp − G_pk·G_kk⁻¹·G_kp; below ``rtol``² the column is dropped.
    (Gram round-off is ~1e-15 here, far below rtol² = 1e-12 for the default rtol.)
    Returns the kept indices and, per dropped index, up to 3 kept columns it is (nearly)
    spanned by.
    """
    P = G.shape[0]
    d = np.sqrt(np.clip(np.diag(G), 0, None))
    good = (d > 0) & np.isfinite(d)
    Gn = G / np.outer(np.where(good, d, 1.0), np.where(good, d, 1.0))
    kept: list[int] = []
    dropped: dict[int, tuple[int, ...]] = {}
    for p in range(P):
        if not good[p]:
            dropped[p] = ()
            continue
        if kept:
            Gkk = Gn[np.ix_(kept, kept)]
            c = _solve_pos(Gkk, Gn[kept, p])
            r2 = float(Gn[p, p] - Gn[p, kept] @ c)
        else:
            c, r2 = np.zeros(0), 1.0
        if r2 < rtol**2:
            big = np.argsort(-np.abs(c))
            dropped[p] = tuple(kept[j] for j in big[:3] if abs(c[j]) > 1e-3 * np.abs(c).max())
            continue
        kept.append(p)
    return kept, dropped


def solve(
    r: np.ndarray,
    A: np.ndarray,
    names: Sequence[str],
    slices: Mapping[str, slice],
    *,
    weights: np.ndarray | None = None,
    stride: int = 1,
    average: int = 1,
    covariance: str = "auto",
    axis_weighting: bool = True,
    n_blocks: int = 30,
    rank_rtol: float = 1e-6,
    on_unobservable: str = "drop",
    plausible: Mapping[str, float] | None = None,
    hac_bandwidth: float | None = None,
    min_excitation_snr: float = 5.0,
    noisy_effects: Sequence[str] = NOISY_REGRESSOR_EFFECTS,
    noise_model=None,
    t_s: np.ndarray | None = None,
    row_t0_s: np.ndarray | None = None,
    row_t1_s: np.ndarray | None = None,
    row_n_eff: np.ndarray | None = None,
) -> LsqFit:
    """Solve r ≈ A·θ jointly over the three axes.

    Parameters
    ----------
    r : ndarray, shape (N, 3)
        Left-hand side, usually measured minus reference rate, rad/s (S frame).
    A : ndarray, shape (N, 3, P)
        Regressors (see :func:`build_design`).
    names : sequence of str, length P
        Column names ``"effect.param[index]"``.
    slices : mapping effect -> slice
    weights : ndarray, shape (N,) or (N, 3), optional
        Non-negative row weights (0 excludes a sample, e.g. a transient). Multiplied by the
        axis weights 1/σ_i² when ``axis_weighting``.
    stride : int
        Use every ``stride``-th sample (downsampling for speed; the covariance is computed
        on the same rows and stays honest through the HAC/block estimator).
    average : int
        Fit weighted block means of ``average`` consecutive rows (after ``stride``) instead
        of the rows: exact for the linear model, keeps nearly all the information of slow
        regressors and cuts memory/time; residual RMS is still reported on all samples.
    covariance : {"auto", "ols", "hac", "newey_west", "block", "noise_model"}
        See the module docstring. ``"noise_model"`` needs ``noise_model`` and the row times
        (``t_s``, or ``row_t0_s``/``row_t1_s``/``row_n_eff`` for rows that are already means).
    axis_weighting : bool
        Two-step feasible WLS: weight axis i by 1/σ̂_i² from a first unweighted pass.
    n_blocks : int
        Number of contiguous blocks for ``"block"``.
    rank_rtol : float
        Relative residual norm below which a column counts as spanned by earlier ones.
    on_unobservable : {"drop", "raise"}
        Drop unobservable columns and report them, or raise :class:`UnobservableError`.
    plausible : mapping effect -> float, optional
        Overrides of :data:`PLAUSIBLE_MAGNITUDE`.
    hac_bandwidth : float, optional
        Fixed Bartlett bandwidth for ``"newey_west"`` (samples after stride); default
        Andrews' plug-in.
    min_excitation_snr : float
        For columns built from measured inputs (``noisy_effects``): the RMS of the column's
        part independent of the other columns over its first-difference noise level
        (std(Δ)/√2, which equals the RMS for white noise) must reach this, else the parameter
        is unobservable (5 → errors-in-variables attenuation below (1/5)² = 4 %).
    noisy_effects : sequence of str
        Effects whose regressors come from measured inputs (accel, temperature).
    noise_model : gyrocore.calib.budget.NoiseModel, optional
        The gyro's noise (identified, e.g. :func:`gyrocore.noise.allan.identify_noise` →
        :meth:`gyrocore.calib.budget.NoiseModel.from_identified`), for ``covariance="noise_model"``:
        the sandwich (AᵀWA)⁻¹·(Σ_i U_iᵀ C_i U_i)·(AᵀWA)⁻¹, U = W·A, C_i the covariance of the
        rows' noise implied by the model (:func:`noise_model_meat`).
    t_s : ndarray, shape (N,), optional
        Sample times, s since the power-up (flicker and random walk start there).
    row_t0_s, row_t1_s, row_n_eff : ndarray, optional
        For rows that are already means of samples (a streaming caller; ``average`` = 1,
        ``stride`` = 1): each row's interval, s since the power-up, and effective sample count
        (n,) or (n, 3); with these ``t_s`` is only used for the sample spacing ``dt``
        (or give ``t_s`` of length 2: [0, dt]).

    Returns
    -------
    LsqFit
    """
    r_all = np.asarray(r, float)
    A_all = np.asarray(A, float)
    N, P = r_all.shape[0], A_all.shape[2]
    _check_solve_args(
        r_all,
        A_all,
        names,
        covariance=covariance,
        noise_model=noise_model,
        t_s=t_s,
        row_t0_s=row_t0_s,
        on_unobservable=on_unobservable,
    )
    stride = max(1, int(stride))
    average = max(1, int(average))
    w_all, idx = _used_rows(r_all, A_all, weights, stride)
    r_, A_, w_ = r_all[idx], A_all[idx], w_all[idx]
    rows_t, dt_s = None, float("nan")
    if covariance == "noise_model":
        rows_t, dt_s = _row_times(N, idx, t_s, row_t0_s, row_t1_s, row_n_eff, average=average, stride=stride)
    if average > 1:
        r_, A_, w_, rows_t = _block_means(r_, A_, w_, rows_t, average)
    n = r_.shape[0]
    plaus = dict(PLAUSIBLE_MAGNITUDE)
    plaus.update(plausible or {})
    kept, dropped, reasons = _observable_columns(
        A_, w_, names, rank_rtol=rank_rtol, noisy_effects=noisy_effects, min_excitation_snr=min_excitation_snr
    )

    # fit, weight the axes, estimate the covariance; drop the parameters whose standard error
    # exceeds their plausible magnitude and refit, until none does
    sigma = np.ones(3)
    for _attempt in range(P + 1):
        th = _wls(A_, r_, kept, w_)
        e = r_ - np.einsum("nip,p->ni", A_[:, :, kept], th)
        if axis_weighting:
            sigma = _axis_sigma(r_, e, w_)
            W = w_ / sigma[None, :] ** 2
            th = _wls(A_, r_, kept, W)
            e = r_ - np.einsum("nip,p->ni", A_[:, :, kept], th)
        else:
            W = w_
        Ak = A_[:, :, kept]
        XtX = np.einsum("nip,ni,niq->pq", Ak, W, Ak, optimize=True)
        cn = np.sqrt(np.diag(XtX))
        cn[cn == 0] = 1.0
        XtX_s = XtX / np.outer(cn, cn)
        ev = np.linalg.eigvalsh(XtX_s)
        cond = float(np.sqrt(ev[-1] / ev[0])) if ev[0] > 0 else float("inf")
        bread = linalg.pinvh(XtX_s) / np.outer(cn, cn)
        ew = e * np.sqrt(W)
        lb_p = ljung_box_p(ew)
        kind = covariance
        if kind == "auto":
            coloured = (np.isfinite(lb_p) and lb_p < 0.01) or any(
                low_frequency_excess(ew[:, i][W[:, i] > 0]) for i in range(3)
            )
            kind = "hac" if coloured else "ols"
        k = len(kept)
        dof = max(int(np.sum(W > 0)) - k, 1)
        cov_k, L = _parameter_covariance(
            kind,
            Ak,
            W,
            e,
            ew,
            bread,
            n=n,
            dof=dof,
            rows_t=rows_t,
            noise_model=noise_model,
            dt_s=dt_s,
            hac_bandwidth=hac_bandwidth,
            n_blocks=n_blocks,
        )
        se_k = np.sqrt(np.clip(np.diag(cov_k), 0, None))
        too_wide = [(j, p) for j, p in enumerate(kept) if se_k[j] > _plausible(plaus, _column_effect(names[p]))]
        if not too_wide:
            break
        for j, p in too_wide:
            eff = _column_effect(names[p])
            reasons[names[p]] = (
                f"standard error {se_k[j]:.3g} exceeds the plausible magnitude {_plausible(plaus, eff):.3g} (too little excitation)"
            )
            dropped[p] = ()
        kept = [p for p in kept if p not in {p for _, p in too_wide}]
        if not kept:
            break
    return _fit_result(
        r_all,
        A_all,
        idx,
        w_all,
        names,
        slices,
        kept=kept,
        th=th,
        cov_k=cov_k,
        reasons=reasons,
        on_unobservable=on_unobservable,
        kind=kind,
        lb_p=lb_p,
        L=L,
        sigma=sigma,
        cond=cond,
        n=n,
        dof=dof,
    )


# ---------------------------------------------------------------------------- the steps of solve
def _fit_result(
    r_all,
    A_all,
    idx,
    w_all,
    names,
    slices,
    *,
    kept,
    th,
    cov_k,
    reasons,
    on_unobservable,
    kind,
    lb_p,
    L,
    sigma,
    cond,
    n,
    dof,
) -> LsqFit:
    """The :class:`LsqFit` of the kept columns (the others: θ = 0, variance ∞), with the
    residual and its RMS over the used rows."""
    P = A_all.shape[2]
    unobs = tuple(names[p] for p in range(P) if p not in kept)
    if unobs and on_unobservable == "raise":
        raise UnobservableError("unobservable parameters: " + "; ".join(f"{u} ({reasons.get(u, '')})" for u in unobs))
    theta = np.zeros(P)
    cov = np.full((P, P), np.nan)
    if kept:
        theta[kept] = th
        cov[np.ix_(kept, kept)] = cov_k
    for p in range(P):
        if p not in kept:
            cov[p, p] = np.inf
    stderr = np.sqrt(np.diag(cov))
    resid = r_all - np.einsum("nip,p->ni", A_all, theta)
    used, wu = resid[idx], w_all[idx]
    rms = np.sqrt(np.sum(wu * used**2, axis=0) / np.maximum(np.sum(wu, axis=0), 1e-300))
    return LsqFit(
        theta=theta,
        names=tuple(names),
        slices=dict(slices),
        cov=cov,
        stderr=stderr,
        cov_kind=kind,
        ljung_box_p=float(lb_p),
        hac_bandwidth=L,
        residual_rad_s=resid,
        residual_rms_rad_s=rms,
        axis_sigma_rad_s=np.asarray(sigma, float),
        rank=len(kept),
        condition=cond if kept else float("inf"),
        unobservable=unobs,
        unobservable_reason={u: reasons.get(u, "") for u in unobs},
        n_rows=int(n),
        dof=int(dof),
    )


def _check_solve_args(r_all, A_all, names, *, covariance, noise_model, t_s, row_t0_s, on_unobservable) -> None:
    """One ``error:`` line for arguments :func:`solve` cannot use."""
    N, P = r_all.shape[0], A_all.shape[2]
    if r_all.shape != (N, 3) or A_all.shape[:2] != (N, 3):
        raise GyroInputError(f"lsq: r has shape {r_all.shape}, A has shape {A_all.shape}; expected (N,3) and (N,3,P)")
    if len(names) != P:
        raise GyroInputError(f"lsq: {len(names)} names for {P} columns")
    if covariance not in ("auto", "ols", "hac", "newey_west", "block", "noise_model"):
        raise GyroInputError(f"unknown covariance '{covariance}' (auto, ols, hac, newey_west, block, noise_model)")
    if covariance == "noise_model" and (noise_model is None or (t_s is None and row_t0_s is None)):
        raise GyroInputError("covariance 'noise_model' needs the noise model and the sample times")
    if on_unobservable not in ("drop", "raise"):
        raise GyroInputError(f"on_unobservable must be 'drop' or 'raise', not '{on_unobservable}'")


def _used_rows(r_all, A_all, weights, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """The (N, 3) weights and the indices of the rows used: every ``stride``-th row with a
    non-zero weight on some axis."""
    N = r_all.shape[0]
    w_all = (
        np.ones((N, 3))
        if weights is None
        else np.broadcast_to(np.asarray(weights, float).reshape(N, -1), (N, 3)).copy()
    )
    if np.any(~np.isfinite(w_all)) or np.any(w_all < 0):
        raise GyroInputError("lsq: weights must be finite and non-negative")
    if not np.all(np.isfinite(r_all)) or not np.all(np.isfinite(A_all)):
        raise GyroInputError("lsq: non-finite values in the data or regressors")
    idx = np.arange(0, N, stride)
    idx = idx[np.any(w_all[idx] > 0, axis=1)]
    if idx.size < 2:
        raise GyroInputError("lsq: fewer than 2 samples with non-zero weight")
    return w_all, idx


def _row_times(N: int, idx, t_s, row_t0_s, row_t1_s, row_n_eff, *, average: int, stride: int):
    """For ``covariance="noise_model"``: each used row's interval (s since the power-up) and
    effective sample count, and the sample spacing dt_s."""
    t_arr = np.asarray(t_s if t_s is not None else [], float)
    dt_s = float(np.median(np.diff(t_arr))) if t_arr.size > 1 else float("nan")
    if row_t0_s is not None:
        if not np.isfinite(dt_s):  # sample spacing from the rows: the shortest span per sample
            ne0 = np.asarray(row_n_eff, float).reshape(N, -1)[:, 0]
            span = np.asarray(row_t1_s, float) - np.asarray(row_t0_s, float)
            ok = ne0 > 0
            dt_s = float(np.min(span[ok] / ne0[ok])) if ok.any() else 1.0
        if average != 1 or stride != 1:
            raise GyroInputError("lsq: row times are for rows that are already means (average=1, stride=1)")
        rows_t = (
            np.asarray(row_t0_s, float)[idx],
            np.asarray(row_t1_s, float)[idx],
            np.broadcast_to(np.asarray(row_n_eff, float).reshape(N, -1), (N, 3))[idx],
        )
    else:
        if t_arr.shape != (N,):
            raise GyroInputError(f"lsq: t_s has shape {t_arr.shape}, expected ({N},)")
        tt = t_arr[idx]
        rows_t = (tt, tt + dt_s, np.ones((idx.size, 3)))
    return rows_t, dt_s


def _block_means(r_, A_, w_, rows_t, average: int):
    """Weighted block means of ``average`` consecutive used rows: the linear model holds
    exactly for the means, white noise shrinks by sqrt(average)."""
    nb = r_.shape[0] // average
    if nb < 2:
        raise GyroInputError(f"lsq: average={average} leaves fewer than 2 rows")
    m = nb * average
    wb = w_[:m].reshape(nb, average, 3)
    ws = wb.sum(axis=1)
    safe = np.where(ws > 0, ws, 1.0)
    r_ = (r_[:m].reshape(nb, average, 3) * wb).sum(axis=1) / safe
    A_ = (A_[:m].reshape(nb, average, 3, -1) * wb[..., None]).sum(axis=1) / safe[..., None]
    if rows_t is not None:  # each row's interval and effective count (Σw)²/Σw²
        w2 = (wb**2).sum(axis=1)
        rows_t = (
            rows_t[0][:m:average],
            rows_t[1][average - 1 : m : average],
            np.where(w2 > 0, ws**2 / np.where(w2 > 0, w2, 1.0), 0.0),
        )
    return r_, A_, ws / average, rows_t


def _observable_columns(A_, w_, names, *, rank_rtol: float, noisy_effects, min_excitation_snr: float):
    """Columns that can be fitted: (kept column indices, {dropped: the columns it is not
    separable from}, {column name: why it was dropped})."""
    # sequential rank test on the (unweighted-by-axis) design
    G_all = np.einsum("nip,ni,niq->pq", A_, w_, A_, optimize=True)
    kept, dropped = _sequential_rank(G_all, rank_rtol)
    reasons: dict[str, str] = {}
    for p, by in dropped.items():
        if by:
            reasons[names[p]] = "not separable from " + ", ".join(names[j] for j in by)
        else:
            reasons[names[p]] = "regressor is zero in the data (no excitation)"

    # columns built from measured inputs (accel, temperature): their independent part must
    # stand above the input's own noise, else the fit is to noise (errors in variables)
    noisy_idx = [p for p in kept if _is_noisy(_column_effect(names[p]), noisy_effects)]
    if noisy_idx and min_excitation_snr > 0:
        sw = np.sqrt(w_)
        drop_noisy = []
        Gk = G_all[np.ix_(kept, kept)]
        for p in noisy_idx:
            j = kept.index(p)
            oth = [q for q in range(len(kept)) if q != j]
            R = A_[:, :, p] * sw
            if oth:
                c = linalg.lstsq(Gk[np.ix_(oth, oth)], Gk[oth, j])[0]
                R = R - np.einsum("nip,p->ni", A_[:, :, [kept[q] for q in oth]], c) * sw
            exc2 = float(np.mean(R**2))
            noise2 = float(np.mean(np.diff(R, axis=0) ** 2)) / 2.0
            snr = np.sqrt(exc2 / noise2) if noise2 > 0 else np.inf
            if snr < min_excitation_snr:
                drop_noisy.append(p)
                reasons[names[p]] = (
                    f"its regressor varies only at the level of its own measurement noise "
                    f"(excitation/noise {snr:.2g} < {min_excitation_snr:g})"
                )
        kept = [p for p in kept if p not in drop_noisy]
    return kept, dropped, reasons


def _wls(A_, r_, cols: list[int], w: np.ndarray) -> np.ndarray:
    """Weighted least squares of r_ on the columns ``cols``: the normal equations of the
    column-equilibrated problem (the columns passed the rank test, so cond² stays far from 1/eps)."""
    Ac = A_[:, :, cols]
    G = np.einsum("nip,ni,niq->pq", Ac, w, Ac, optimize=True)
    b = np.einsum("nip,ni,ni->p", Ac, w, r_, optimize=True)
    cn = np.sqrt(np.diag(G))
    cn[cn == 0] = 1.0
    return _solve_pos(G / np.outer(cn, cn), b / cn) / cn


def _axis_sigma(r_, e, w_) -> np.ndarray:
    """Per-axis residual σ̂ of a first pass, for the axis weights 1/σ̂² (feasible WLS)."""
    sig = np.sqrt(np.sum(w_ * e**2, axis=0) / np.maximum(np.sum(w_ > 0, axis=0), 1))
    # an exact fit (noise-free data) has nothing to weight: unit weights; otherwise a
    # relative floor keeps an exactly fitted axis from getting an infinite weight
    smax = float(sig.max())
    # ... and so is a residual at the rounding level of the data (64 eps·max|r|) or
    # below 1e-100 rad/s (no instrument's noise; 1/σ² of the 1e-9 floor then stays
    # below 1e218, no overflow: hypothesis found b = 1.4e-146 rad/s, σ ~ 1e-150)
    exact = smax <= max(64.0 * np.finfo(float).eps * float(np.max(np.abs(r_), initial=0.0)), 1e-100)
    return np.ones(3) if smax == 0.0 or exact else np.maximum(sig, 1e-9 * smax)


def _parameter_covariance(
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


#: Window length of the chunked design in :func:`fit_effects` (rows); records longer than
#: 4 windows fitted with ``average`` > 1 take the chunked path (bounded memory).
CHUNK_ROWS: int = 32768


def fit_effects(
    r: np.ndarray,
    effects: Sequence[str],
    inp: E.ModelInputs,
    *,
    orders: Mapping[str, int] | None = None,
    chunk_rows: int | None = CHUNK_ROWS,
    keep_residual: bool = True,
    overwrite_r: bool = False,
    residual_sink=None,
    **options,
) -> LsqFit:
    """Fit the linearised ``effects`` to r = y − ω_ref jointly (see :func:`solve`).

    Parameters
    ----------
    r : ndarray, shape (N, 3), or RowSource
        Measured minus reference rate, rad/s, S frame; or a :class:`RowSource` that gives r
        and the model inputs a window at a time (a record on disk; ``inp`` is then unused
        and the chunked path is taken whenever ``average`` > 1).
    effects : sequence of str
        Catalogue effects with regressors (``effects.design``); the order matters for the
        observability test (an earlier effect keeps a column that a later one duplicates).
    inp : ModelInputs
        ``omega_S_rad_s`` = reference rate; ``f_S_m_s2``/``temp_c`` when the effects need them.
    orders : mapping, optional
        Thermal polynomial orders.
    chunk_rows : int or None
        With ``average`` > 1 and N > 4·``chunk_rows``, the design (N, 3, P) is never held
        whole: it is built in windows of ``chunk_rows`` samples (one sample of overlap for
        the time derivatives of ``time_offset``/``bias_temp_rate``; the thermal T0 and the
        power-up time of the whole record), reduced to the weighted block means that
        ``solve(average=)`` fits, and the full-resolution residual is computed window by
        window from θ. Same result as the whole-array path to float rounding; memory
        O(chunk_rows·P + N_blocks·P) instead of O(N·P). None: always the whole-array path.
    keep_residual : bool
        False: the result's ``residual_rad_s`` is empty, shape (0, 3) (its RMS is still
        computed), so a fit whose residual is not used (e.g. an order test) holds no
        (N, 3) array.
    overwrite_r : bool
        Chunked path only: write the residual into ``r`` (a float64 (N, 3) array the caller
        no longer needs) and return it as ``residual_rad_s``, saving one (N, 3) array —
        like scipy's ``overwrite_a``.
    residual_sink : callable, optional
        ``residual_sink(a, b, e)`` receives the full-resolution residual of rows a:b
        (shape (b − a, 3), rad/s) window by window (chunked path, taken whenever a sink is
        given), e.g. to write it to disk instead of holding (N, 3) in memory.
    **options
        Keyword options of :func:`solve`.
    """
    average = max(1, int(options.get("average", 1)))
    if isinstance(r, RowSource):
        if average > 1 or residual_sink is not None:
            return _fit_effects_chunked(
                r,
                effects,
                None,
                orders=orders,
                chunk_rows=int(chunk_rows or CHUNK_ROWS),
                keep_residual=keep_residual,
                residual_sink=residual_sink,
                **options,
            )
        # no block means (few rows with a weight): the whole-array path on the rows read back
        r, inp = r.r_rows(0, r.n), r.inputs(0, r.n)
    n = int(np.shape(r)[0]) if np.ndim(r) >= 1 else 0
    if residual_sink is not None or (chunk_rows and average > 1 and n > 4 * int(chunk_rows)):
        return _fit_effects_chunked(
            r,
            effects,
            inp,
            orders=orders,
            chunk_rows=int(chunk_rows or CHUNK_ROWS),
            keep_residual=keep_residual,
            overwrite_r=overwrite_r,
            residual_sink=residual_sink,
            **options,
        )
    A, names, slices = build_design(effects, inp, orders=orders)
    fit = solve(r, A, names, slices, **options)
    if not keep_residual:
        fit = dataclasses.replace(fit, residual_rad_s=np.zeros((0, 3)))
    return fit


def _window_inputs(inp: E.ModelInputs, lo: int, hi: int) -> E.ModelInputs:
    """Rows lo:hi of ``inp``; the power-up time stays that of the whole record."""
    kw = {}
    for f in dataclasses.fields(inp):
        v = getattr(inp, f.name)
        kw[f.name] = None if v is None else np.asarray(v)[lo:hi]
    if inp.t_since_power_up_s is None:
        t = np.asarray(inp.t_s, float)
        kw["t_since_power_up_s"] = t[lo:hi] - t[0]
    return E.ModelInputs(**kw)


class RowSource:
    """Rows of a fit's left-hand side r = y − ω_ref and of its model inputs, a window at a time.

    The chunked (block-mean) path of :func:`fit_effects` reads its data only through this
    interface, so a record held on disk (:class:`gyrocore.calib.stream.SpillRows`: the columns of a
    long data file, read back a window at a time) is fitted with exactly the arithmetic of the
    in-memory arrays (:class:`ArrayRows`) — same windows, same sums, same numbers.

    Attributes
    ----------
    n : int
        Number of rows N.
    has_temp : bool
        Whether the inputs carry a temperature column.
    """

    n: int = 0
    has_temp: bool = False

    def r_rows(self, a: int, b: int) -> np.ndarray:
        """r on rows a:b, rad/s, shape (b − a, 3) (a fresh or read-only array)."""
        raise NotImplementedError

    def inputs(self, lo: int, hi: int) -> E.ModelInputs:
        """Model inputs of rows lo:hi (``t_since_power_up_s`` counted from the record's start)."""
        raise NotImplementedError

    def t_rows(self, a: int, b: int) -> np.ndarray:
        """Sample times of rows a:b, s."""
        return np.asarray(self.inputs(a, b).t_s, float)

    def temp_mean_c(self) -> float | None:
        """Mean temperature over all N rows, °C (the thermal T0 of :func:`gyrocore.effects.registry.design`)."""
        raise NotImplementedError


class ArrayRows(RowSource):
    """:class:`RowSource` over in-memory arrays ``r`` (N, 3) and ``inp``."""

    def __init__(self, r: np.ndarray, inp: E.ModelInputs) -> None:
        self.r = r
        self.inp = inp
        self.n = int(np.shape(r)[0])
        self.has_temp = inp.temp_c is not None

    def r_rows(self, a: int, b: int) -> np.ndarray:
        return self.r[a:b]

    def inputs(self, lo: int, hi: int) -> E.ModelInputs:
        return _window_inputs(self.inp, lo, hi)

    def t_rows(self, a: int, b: int) -> np.ndarray:
        return np.asarray(self.inp.t_s, float)[a:b]

    def temp_mean_c(self) -> float | None:
        return None if self.inp.temp_c is None else float(np.mean(np.asarray(self.inp.temp_c, float)))


def _window_design(effects, src: RowSource, orders, t0_c, a: int, b: int, n: int):
    """Design rows a:b of the whole record, built on a:b plus one neighbour each side (so
    central differences at the window edges equal those of the whole record)."""
    lo, hi = max(a - 1, 0), min(b + 1, n)
    A, names, slices = build_design(effects, src.inputs(lo, hi), orders=orders, t0_c=t0_c)
    A = A[a - lo : a - lo + (b - a)]
    if not np.all(np.isfinite(A)):
        raise GyroInputError("lsq: non-finite values in the data or regressors")
    return A, names, slices


def _fit_effects_chunked(
    r,
    effects,
    inp,
    *,
    orders,
    chunk_rows: int,
    keep_residual: bool = True,
    overwrite_r: bool = False,
    residual_sink=None,
    weights=None,
    stride: int = 1,
    average: int = 1,
    **options,
) -> LsqFit:
    """:func:`fit_effects` for long records: block means built window by window (see there).

    ``r`` is an (N, 3) array (with ``inp``) or a :class:`RowSource` (``inp`` unused)."""
    if isinstance(r, RowSource):
        src = r
        r_arr = None
    else:
        r_arr = np.asarray(r, float)
        if r_arr.ndim != 2 or r_arr.shape[1] != 3:
            raise GyroInputError(f"lsq: r has shape {r_arr.shape}; expected (N,3)")
        if inp.n != r_arr.shape[0]:
            raise GyroInputError(f"lsq: r has {r_arr.shape[0]} rows, the model inputs {inp.n}")
        if not np.all(np.isfinite(r_arr)):
            raise GyroInputError("lsq: non-finite values in the data or regressors")
        src = ArrayRows(r_arr, inp)
    N = src.n
    stride = max(1, int(stride))
    average = max(1, int(average))
    w_all = np.ones((N, 3)) if weights is None else np.broadcast_to(np.asarray(weights, float).reshape(N, -1), (N, 3))
    if np.any(~np.isfinite(w_all)) or np.any(w_all < 0):
        raise GyroInputError("lsq: weights must be finite and non-negative")
    keep = np.zeros(N, bool)  # the rows solve() uses: every stride-th with a non-zero weight
    keep[::stride] = True
    keep &= np.any(w_all > 0, axis=1)
    n_used = int(np.count_nonzero(keep))
    if n_used < 2:
        raise GyroInputError("lsq: fewer than 2 samples with non-zero weight")
    nb = n_used // average
    if nb < 2:
        raise GyroInputError(f"lsq: average={average} leaves fewer than 2 rows")
    m = nb * average
    t0_c = src.temp_mean_c() if src.has_temp else None
    # pass 1: weighted block sums of r and A over `average` consecutive used rows (the
    # same sums, in the same order, as solve(average=) except where a block straddles two
    # windows)
    Sr = Sw = SA = None
    names = slices = None
    # per block mean: Σw² (effective samples (Σw)²/Σw²) and the time span it averages — the
    # row intervals of a noise-model covariance (forwarded to solve with covariance="noise_model")
    Sw2 = np.zeros((nb, 3))
    T0 = np.full(nb, np.inf)
    T1 = np.full(nb, -np.inf)
    t_first = float(src.t_rows(0, 1)[0])
    j0 = 0  # used rows before the window
    for a in range(0, N, chunk_rows):
        b = min(a + chunk_rows, N)
        rows = a + np.flatnonzero(keep[a:b])
        j1 = min(j0 + rows.size, m)
        rows = rows[: j1 - j0]
        if rows.size == 0:
            j0 += rows.size
            if j0 >= m:
                break
            continue
        A, names, slices = _window_design(effects, src, orders, t0_c, a, b, N)
        wr = w_all[rows]
        A = A[rows - a]
        A *= wr[..., None]
        rw = src.r_rows(a, b)[rows - a]
        if r_arr is None and not np.all(np.isfinite(rw)):
            raise GyroInputError("lsq: non-finite values in the data or regressors")
        rw = rw * wr
        if SA is None:
            SA = np.zeros((nb, 3, A.shape[2]))
            Sr = np.zeros((nb, 3))
            Sw = np.zeros((nb, 3))
        k = np.arange(j0, j1) // average
        starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
        kb = k[starts]
        SA[kb] += np.add.reduceat(A, starts, axis=0)
        Sr[kb] += np.add.reduceat(rw, starts, axis=0)
        Sw[kb] += np.add.reduceat(wr, starts, axis=0)
        Sw2[kb] += np.add.reduceat(wr * wr, starts, axis=0)
        tr = src.t_rows(a, b)[rows - a] - t_first
        ends = np.r_[starts[1:], k.size] - 1
        np.minimum.at(T0, kb, tr[starts])
        np.maximum.at(T1, kb, tr[ends])
        del A, rw, wr
        j0 = j1
        if j0 >= m:
            break
    safe = np.where(Sw > 0, Sw, 1.0)
    if options.get("covariance") == "noise_model":
        dt = (float(src.t_rows(N - 1, N)[0]) - t_first) / max(N - 1, 1)
        options = dict(
            options,
            row_t0_s=T0,
            row_t1_s=T1 + dt,
            row_n_eff=np.where(Sw2 > 0, Sw**2 / np.where(Sw2 > 0, Sw2, 1.0), 0.0),
        )
    fit = solve(Sr / safe, SA / safe[..., None], names, slices, weights=Sw / average, stride=1, average=1, **options)
    del SA
    # pass 2: the residual r − A·θ at full resolution and its RMS over the used rows
    in_place = keep_residual and overwrite_r and r_arr is not None and r_arr is r and r_arr.flags.writeable
    resid, rms = _chunked_residual(
        fit.theta,
        effects,
        src,
        orders,
        t0_c,
        chunk_rows=chunk_rows,
        keep=keep,
        w_all=w_all,
        r_arr=r_arr if keep_residual else None,
        in_place=in_place,
        residual_sink=residual_sink,
    )
    return dataclasses.replace(fit, residual_rad_s=resid, residual_rms_rad_s=rms)


def _chunked_residual(
    theta, effects, src, orders, t0_c, *, chunk_rows: int, keep, w_all, r_arr, in_place: bool, residual_sink
):
    """The residual r − A·θ a window at a time: into ``r_arr``'s shape ((0, 3) when ``r_arr`` is
    None; into ``r_arr`` itself when ``in_place``), to ``residual_sink``, and its weighted RMS
    over the used rows ``keep`` (rad/s, (3,))."""
    N = src.n
    if r_arr is None:
        resid = np.zeros((0, 3))
    else:
        resid = r_arr if in_place else np.empty_like(r_arr)  # window a:b reads only r[a:b]
    num = np.zeros(3)
    den = np.zeros(3)
    for a in range(0, N, chunk_rows):
        b = min(a + chunk_rows, N)
        A, _, _ = _window_design(effects, src, orders, t0_c, a, b, N)
        e = src.r_rows(a, b) - np.einsum("nip,p->ni", A, theta)
        del A
        if r_arr is not None:
            resid[a:b] = e
        if residual_sink is not None:
            residual_sink(a, b, e)
        sel = keep[a:b]
        wu = w_all[a:b][sel]
        num += np.sum(wu * e[sel] ** 2, axis=0)
        den += np.sum(wu, axis=0)
    return resid, np.sqrt(num / np.maximum(den, 1e-300))
