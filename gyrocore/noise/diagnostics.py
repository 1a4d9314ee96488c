"""Checks on a measured Allan variance: goodness of fit, the sensor's low-pass, narrowband lines.

- :func:`goodness_of_fit` — is the measured Allan variance consistent with a fitted model?
- :func:`bandwidth_start` — the first octave above the sensor's low-pass (the fit starts there).
- :func:`line_avar` — narrowband lines of a still record and their Allan variance (removed
  before the fit: a sinusoid is not sensor noise).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.stats

from .avar import avar_covariance, term_avar

__all__ = ["ALPHA_GOF", "FitCheck", "goodness_of_fit", "n_params", "bandwidth_start", "Lines", "line_avar"]

_Z95 = float(scipy.stats.norm.isf(0.025))


#: level of the goodness-of-fit test of the selected model (``fit_ok`` false below it)
ALPHA_GOF = 0.01
#: one-sided level of the test that the shortest scales are shaped by the sensor's low-pass
#: (anti-aliasing/DLPF, integration): a white-noise octave pair whose Allan variance falls by
#: significantly less than the factor 2 of white rate noise (white angle noise only steepens it)
ALPHA_BANDWIDTH = 0.001


@dataclass(frozen=True, eq=False)
class FitCheck:
    """Goodness of fit of a fitted Allan variance against the measured one.

    Attributes
    ----------
    stat : float
        zᵀR⁻¹z with z_j = Φ⁻¹(F_{χ²(ν_j)}(ν_j σ̂²_j / σ²_j)) (probability-integral transform of
        each point with its exact chi-square law, ν_j the model's EDF) and R the model
        correlation between scales; ≈ χ²(dof) when the model holds.
    dof : int
        Scales fitted minus free parameters (positive coefficients, and τc).
    p_value : float
        P(χ²(dof) ≥ stat).
    z : ndarray (M,)
        Per-scale normal scores (positive: the data above the model).
    misses : int
        Scales outside their 95 % chi-square interval (|z| > 1.96).
    p_misses : float
        P(Binomial(M, 0.05) ≥ misses) — the per-point view of the same question (points are
        correlated, so this is indicative; ``p_value`` is the test).
    ok : bool
        ``p_value ≥`` :data:`ALPHA_GOF`.
    """

    stat: float
    dof: int
    p_value: float
    z: np.ndarray
    misses: int
    p_misses: float
    ok: bool


def _pit_z(avar: np.ndarray, model: np.ndarray, edf: np.ndarray) -> np.ndarray:
    """Normal scores of σ̂²_j under σ̂²_j ~ σ²_j χ²_ν/ν (each tail from its own side: exact far out)."""
    x = np.asarray(edf, float) * np.asarray(avar, float) / np.maximum(np.asarray(model, float), np.finfo(float).tiny)
    lo = scipy.stats.chi2.cdf(x, edf)
    hi = scipy.stats.chi2.sf(x, edf)
    with np.errstate(divide="ignore"):
        z = np.where(lo < hi, scipy.stats.norm.ppf(lo), scipy.stats.norm.isf(hi))
    return np.clip(z, -37.0, 37.0)


def goodness_of_fit(avar: np.ndarray, model: np.ndarray, cov: np.ndarray, edf: np.ndarray, n_params: int) -> FitCheck:
    """Is the measured Allan variance consistent with the fitted model?

    Why not the selection's log-space χ²: log σ̂² with ν ≈ 2–6 (the last octaves) has a thin
    upper tail, so a model 50× below a long-τ point (tomisuarez2 y, N alone) scored z ≈ 2.8 there;
    its exact chi-square tail puts it beyond z = 10. The probability-integral transform keeps each
    point's exact marginal law and the Gaussian-copula correlation of the model (as the
    simulations of :func:`expected_z`), so zᵀR⁻¹z ≈ χ²(M − p) under the model (p fitted
    parameters; the selection, which picks the best-fitting subset, only makes it conservative).

    Parameters
    ----------
    avar, model : ndarray (M,)
        Measured and fitted Allan variance, (rad/s)².
    cov : ndarray (M, M)
        Model covariance of the estimates (:func:`avar_covariance`); only its correlation is used.
    edf : ndarray (M,)
        EDF of each scale under the model.
    n_params : int
        Free parameters of the fit.
    """
    z = _pit_z(avar, model, edf)
    d = np.sqrt(np.diag(cov))
    R = cov / np.outer(d, d)
    stat = float(z @ np.linalg.solve(R, z))
    dof = max(int(z.size - n_params), 1)
    p = float(scipy.stats.chi2.sf(stat, dof))
    misses = int(np.sum(np.abs(z) > _Z95))
    p_m = float(scipy.stats.binom.sf(misses - 1, z.size, 0.05)) if misses else 1.0
    return FitCheck(stat=stat, dof=dof, p_value=p, z=z, misses=misses, p_misses=p_m, ok=bool(p >= ALPHA_GOF))


def n_params(coef: np.ndarray, tc: float | None, sub: Sequence[int]) -> int:
    return int(sum(1 for i in sub if coef[i] > 0) + (1 if (5 in sub and tc and coef[5] > 0) else 0))


def bandwidth_start(avar: np.ndarray, m: np.ndarray, n_samples: int, rate_hz: float) -> int:
    """Index of the first scale above the sensor's low-pass (0 when none is seen).

    A gyro's output is low-pass filtered (digital LPF, anti-aliasing, integration over the
    output interval). Below a few filter time constants its Allan variance falls by less than
    the factor 2 per octave of white rate noise (a first-order filter of time constant τf:
    σ²(τ) ≈ N²/τ · (1 − 1.5 τf/τ)); none of the model's terms has that shape — white angle
    noise Q steepens the fall, the long-τ terms are negligible at the sample scale — so a fit
    over those octaves is misspecified where the EDF is largest (PX4 sample.ulg at 250 Hz:
    σ̂²(8 ms)/σ̂²(4 ms) = 0.99; the fit took a flicker floor of 5e-4 rad/s for it and
    reported N at a quarter of its value).

    Test of octave pair (m_k, m_{k+1}): d_k = log(σ̂²_{k+1}/σ̂²_k) − log(white ratio m_k/m_{k+1}),
    Var d = 2/ν_k + 2/ν_{k+1} − 4ρ/√(ν_kν_{k+1}) with the white-noise EDF and correlation;
    low-pass when d_k > z_{1−α}·sd (α = :data:`ALPHA_BANDWIDTH`, one-sided) — unless the excess
    *rises*: a low-pass deficit −κN²/τ² gives d_k ≈ κ/(2m), falling by half per octave, while
    every term of the model that rises above white at the short scales — flicker, random walk, a
    Gauss–Markov hump (and Q: d < 0 rising to 0) — gives a d_k that grows with the octave (its
    share of σ² doubles per octave or more). So nothing is cut when the GLS slope of d_k over the
    first 5 pairs is significantly positive (level α), and the cut stops at the first pair whose
    excess exceeds the one before. Without this a flicker floor 1.5 % of σ² at the first octave
    (N + B + K with a 5-octave plateau, 2 h at 20 Hz: z of d_k = 3.3, 4.6, 5.0, 7.2, …) was taken
    for a low-pass at *every* pair and the fit started at τ = 100 s, with N reported at 4–9× its
    truth. Pairs are tested from the first one up; when the first is flagged, the fit
    starts above the first pair that is not (at least 6 scales kept), where the remaining low-pass
    deficit −κN²/τ² is fitted in place of Q (method suffix "+lp"). On white noise the first pair
    is flagged with probability ≤ α.
    """
    avar = np.asarray(avar, float)
    m = np.asarray(m, np.int64)
    if m.size < 8:
        return 0
    coef = np.zeros(6)
    coef[1] = float(avar[0]) * m[0] / rate_hz  # white level; only the shape matters
    white = term_avar(m, rate_hz) @ coef
    C, edf, _a = avar_covariance(m, int(n_samples), rate_hz, coef, None, white)
    d_ = np.sqrt(np.diag(C))
    R = C / np.outer(d_, d_)
    z_lim = float(scipy.stats.norm.isf(ALPHA_BANDWIDTH))
    # log σ̂² has variance 2/ν and covariance 2ρ/√(ν_iν_j) (white-noise EDF and correlation)
    V = 2.0 * R / np.sqrt(np.outer(edf, edf))

    def d_of(j: int) -> float:
        return math.log(avar[j + 1] / avar[j]) - math.log(white[j + 1] / white[j])

    if m.size - 8 < 1:
        return 0
    # Rising, not fading: the excess of the first J pairs regressed on the pair index (GLS with
    # the covariance of the differences, Cov d = A V Aᵀ); a slope significantly > 0 is the
    # long-τ terms' growing share, and then nothing is cut. The slope uses J pairs at once: a
    # pair-by-pair "does it fade" test had too little power on a 50-s record (IMU-TK Xsens:
    # d = 0.135, 0.073, 0.023, … a low-pass the old test cut and that one kept).
    J = min(5, m.size - 7)
    A = np.zeros((J, m.size))
    for j in range(J):
        A[j, j], A[j, j + 1] = -1.0, 1.0
    Vd = A @ V @ A.T
    dd = np.array([d_of(j) for j in range(J)])
    X = np.column_stack([np.ones(J), np.arange(J, dtype=float)])
    Wd = np.linalg.inv(Vd)
    cov_b = np.linalg.inv(X.T @ Wd @ X)
    slope = float((cov_b @ X.T @ Wd @ dd)[1])
    if slope > z_lim * math.sqrt(max(float(cov_b[1, 1]), 1e-300)):
        return 0
    k = 0
    while k < m.size - 8:
        d = d_of(k)
        var = V[k, k] + V[k + 1, k + 1] - 2.0 * V[k, k + 1]
        if not d > z_lim * math.sqrt(max(var, 1e-300)):
            break
        k += 1
        if d_of(k) > d:  # the excess stopped fading: the long-τ terms take over from here
            break
    # the fit starts above the last pair the test looked at: where the test stops depends on the
    # noise of that pair (it stops when σ̂² of its upper octave happens to be low), so fitting
    # that octave biased N low (a first-order filter of 1.5 samples: z of N −1.9 on average)
    return k + 2 if k > 0 else 0


#: family-wise level (over the periodogram's bins) at which a narrowband line is detected
ALPHA_LINE = 0.001


@dataclass(frozen=True, eq=False)
class Lines:
    """Narrowband lines found in a still record (:func:`line_avar`).

    Attributes
    ----------
    freqs_hz : tuple of float
        Peak frequency of each line, Hz.
    rms : tuple of float
        RMS of each line (√ of its excess power over the noise floor), signal units (rad/s).
    avar : ndarray (M,)
        Their Allan variance at the requested factors, (rad/s)².
    """

    freqs_hz: tuple[float, ...]
    rms: tuple[float, ...]
    avar: np.ndarray


def line_avar(x: np.ndarray, rate_hz: float, m: np.ndarray) -> Lines:
    """Narrowband lines (vibration, interference) of a still rate signal and their Allan variance.

    A sinusoid is not sensor noise, yet it has an Allan variance: A²sin⁴(πmν)/(m²sin²πν) for
    amplitude A at ν cycles/sample (the Haar filter |H_m(ν)|²/2 = 2sin⁴(πmν)/(m²sin²πν) times its
    variance A²/2), whose envelope falls as 1/τ² — it passes for white angle noise Q at long τ and
    breaks the fit at the short scales (the sunsided MPU-6050 logs: a 31.4-Hz line on z, 30–280×
    the floor, put the second octave 5.7 σ above the fitted model and was reported as Q).

    Welch periodogram (Hann, 50 % overlap, 2^k samples per segment, 64 … 1024, ≥ 63 segments:
    a line that wanders over a few tenths of a Hz stays inside ±4 bins):
    each bin over the floor is ~χ²_ν/ν, ν ≈ 2K/1.056 for K segments (Welch 1967, Hann 50 %
    overlap). The floor is the *higher* of the two one-sided floors — the median of the bins 5–24
    below and of the bins 5–24 above, each divided by the median of χ²_ν/ν: a line stands above
    the noise on both of its sides, whereas a red spectrum (flicker, random walk: 1/f, 1/f²) stands
    above its higher-frequency side at every low bin, and a floor from that side alone (or from
    both pooled, or mirrored at 0 Hz) took the red rise of the lowest bins for a line
    (a "line" at bin 2, 0.039 Hz, on every axis of a 2-h N + B + K record at 20 Hz, whose removal
    took 20–33 % of the Allan variance off the flicker plateau and put B at 0.6× its truth). Bins 0
    and 1 (the mean and each segment's linear detrend) enter no floor, and a bin is tested only
    with ≥ 3 bins on its low side (bin ≥ 10: f ≥ 10·rate/segment; below, the noise model keeps
    whatever is there). Bins above the
    1 − α/n_bins quantile (family-wise level :data:`ALPHA_LINE`) mark lines; each line's excess
    power (bins within ±4 of a marked bin: the Hann main lobe and a little wander) gives its Allan variance
    Σ_b excess_b·Δf·|H_m(ν_b)|²/2 — subtracted from the measured Allan variance, exact in
    expectation because line and noise are independent.

    Parameters
    ----------
    x : ndarray (n,)
        Rate samples (rad/s), evenly spaced.
    rate_hz : float
    m : ndarray (M,) of int
        Averaging factors.
    """
    import scipy.signal

    x = np.asarray(x, float)
    m = np.asarray(m, float)
    none = Lines((), (), np.zeros(m.size))
    n = x.size
    if n < 32 * 64:
        return none
    seg = min(1 << int(math.floor(math.log2(n // 32))), 1024)
    f, p = scipy.signal.welch(x - x.mean(), fs=rate_hz, window="hann", nperseg=seg, noverlap=seg // 2, detrend="linear")
    k_seg = (n - seg) // (seg // 2) + 1
    nu = 2.0 * k_seg / 1.056
    # the floor beside each bin: median of the bins 5 … 24 away on both sides (40 bins). A line
    # (its Hann main lobe ±2 bins, plus a wander of ±2 bins: the sunsided 31.4-Hz line moves over
    # ±0.2 Hz in 10 min) stands above it and its power is summed over ±4 bins; a bump of coloured
    # noise wider than ~10 bins lifts its own ring too and is left to the noise model (PX4 y: a
    # 2–6 Hz bump, 1.4× a ±32-bin running median, was taken for a line and moved N by 9 %)
    inner_r, outer_r = 5, 24
    # one-sided rings; bins 0 and 1 (mean, per-segment linear detrend) and bins past Nyquist are
    # no floor (NaN). The floor is the higher side: never below the pooled median of both rings
    # (the median of a union lies between the medians of its parts), so this detects a subset
    # of what a two-sided pooled floor detects; on a flat spectrum the max of two 20-bin medians
    # is ≈ 1–2 % above the level (their sd ≈ 1.25·√(2/ν)/√20), a slightly conservative test.
    q = p.astype(float).copy()
    q[:2] = np.nan
    pad = np.pad(q, outer_r, mode="constant", constant_values=np.nan)
    win = np.lib.stride_tricks.sliding_window_view(pad, 2 * outer_r + 1)
    low = win[:, 0 : outer_r - inner_r + 1]
    high = win[:, outer_r + inner_r : 2 * outer_r + 1]
    n_low = np.sum(np.isfinite(low), axis=1)
    n_high = np.sum(np.isfinite(high), axis=1)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rings at the edges
        f_low = np.where(n_low > 0, np.nanmedian(np.where(n_low[:, None] > 0, low, 0.0), axis=1), np.nan)
        f_high = np.where(n_high > 0, np.nanmedian(np.where(n_high[:, None] > 0, high, 0.0), axis=1), np.nan)
        # the noise level UNDER a line: the pooled median of both rings where both exist (the
        # level between its two sides; on a sloped spectrum — a sensor low-pass — the higher side
        # alone overstates it and understates the line: the 31-Hz line of the sunsided MPU-6050 z
        # lost 7 % of its rms and its Allan variance then failed the fit's goodness-of-fit test)
        pooled = np.nanmedian(np.where((n_low + n_high)[:, None] > 0, np.concatenate([low, high], axis=1), 0.0), axis=1)
    median_factor = scipy.stats.chi2.median(nu) / nu
    # detection: the higher side (a line stands above the noise on both of its sides)
    floor = np.fmax(f_low, f_high) / median_factor
    inner = (f > 0) & (f < rate_hz / 2) & (n_low >= 3) & np.isfinite(floor)
    floor = np.where(np.isfinite(floor), floor, p)
    level = np.where((n_low > 0) & (n_high > 0), pooled / median_factor, floor)
    thr = scipy.stats.chi2.isf(ALPHA_LINE / max(int(inner.sum()), 1), nu) / nu
    hot = inner & (p > thr * floor)
    if not np.any(hot):
        return none
    near = np.convolve(hot.astype(int), np.ones(2 * inner_r - 1, int), mode="same") > 0
    near &= inner
    df = f[1] - f[0]
    excess = np.where(near, p - level, 0.0) * df  # unbiased (no clipping of the bins' noise)
    v = f / rate_hz
    s = np.sin(np.pi * v)
    H2 = np.zeros((m.size, f.size))
    ok = s > 0
    H2[:, ok] = 4.0 * np.sin(np.pi * m[:, None] * v[None, ok]) ** 4 / (m[:, None] ** 2 * s[None, ok] ** 2)
    avar = np.maximum(0.5 * H2 @ excess, 0.0)
    # one entry per contiguous group of marked bins
    freqs, rms = [], []
    idx = np.flatnonzero(near)
    groups = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)
    for g_ in groups:
        if not np.any(hot[g_]):
            continue
        freqs.append(float(f[g_][np.argmax(p[g_])]))
        rms.append(float(math.sqrt(max(excess[g_].sum(), 0.0))))
    return Lines(tuple(freqs), tuple(rms), avar)
