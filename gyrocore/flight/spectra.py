"""The spectral estimator under the vibration analysis: Hann windows, their degrees of freedom, peaks.

Hand-written on top of numpy's FFT because Welch's average hides the per-window throttle: Hann
windows of ``nperseg`` samples, 50 % overlap, one-sided PSD per window ((unit)²/Hz); windows
holding a time gap are dropped (:func:`hann_windows`). Averaged periodograms of K windows with
50 % overlap Hann have ν ≈ 2K/(1 + 2ρ²) degrees of freedom, ρ = 0.167 the window overlap
correlation (Percival & Walden 1993, §6.17) (:func:`dof`).

Peaks (:func:`find_peaks`): bins whose PSD exceeds a running-median baseline by the χ²_ν
quantile at 1 − 0.001/M (Bonferroni over the M bins searched); frequency by parabolic
interpolation of log PSD; line power = PSD excess over the baseline summed over ±2 bins × Δf,
divided by the Hann window's capture of a tone in those bins; its standard error from the
spread of the per-window line power and the baseline's own χ² scatter.
:mod:`gyrocore.flight.vibration` bands the windows by throttle and links the peaks into lines.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import signal, stats
from scipy.ndimage import median_filter

from gyrocore.errors import GyroInputError

AXES = ("x", "y", "z")
#: Equivalent-dof correlation of 50 %-overlapped Hann windows (Percival & Walden 1993, Table 292).
RHO_HANN_50 = 0.167
#: Hann window equivalent noise bandwidth, bins.
ENBW_HANN = 1.5


def dof(k: int) -> float:
    """Degrees of freedom of an average of ``k`` 50 %-overlapped Hann periodograms."""
    return 2.0 * k / (1.0 + 2.0 * RHO_HANN_50**2)


@dataclass(frozen=True)
class Windows:
    f_hz: np.ndarray  # (M,)
    psd: np.ndarray  # (K, M, 3)   (unit)²/Hz
    band_var: np.ndarray  # (K,) mean of the band variable in each window
    rotor_hz: np.ndarray | None  # (K,) mean rotor frequency, Hz
    rate_hz: float
    nperseg: int


def hann_windows(t_s, x, band_var, rotor_hz, airborne, *, nperseg: int, rate_hz: float) -> Windows:
    """Hann windows (50 % overlap) over gap-free airborne runs; one-sided PSD per window."""
    dt = np.diff(t_s)
    med = float(np.median(dt))
    gap = np.concatenate([[False], np.abs(dt - med) > 0.5 * med])
    # runs of consecutive usable samples
    usable = airborne.copy()
    breaks = np.nonzero(gap | ~usable)[0]
    starts = np.concatenate([[0], breaks])
    ends = np.concatenate([breaks, [t_s.size]])
    step = nperseg // 2
    win = signal.windows.hann(nperseg, sym=False)
    scale = 1.0 / (rate_hz * np.sum(win**2))
    psds, bvs, rhs = [], [], []
    for s0, e0 in zip(starts, ends):
        s0 = s0 if (s0 == 0 or not gap[s0]) else s0  # a gap sample starts a new run
        if not usable[s0]:
            s0 += 1
        n = e0 - s0
        if n < nperseg:
            continue
        for a in range(s0, e0 - nperseg + 1, step):
            seg = x[a : a + nperseg]
            seg = seg - seg.mean(axis=0)
            X = np.fft.rfft(seg * win[:, None], axis=0)
            p = (np.abs(X) ** 2) * scale
            p[1:-1] *= 2.0 if nperseg % 2 == 0 else 1.0
            if nperseg % 2:
                p[1:] *= 2.0
            psds.append(p)
            bvs.append(float(np.mean(band_var[a : a + nperseg])) if band_var is not None else 0.0)
            if rotor_hz is not None:
                rhs.append(float(np.mean(rotor_hz[a : a + nperseg])))
    if not psds:
        raise GyroInputError(
            f"no gap-free airborne stretch of {nperseg} samples ({nperseg / rate_hz:.2f} s) to analyse"
        )
    f = np.fft.rfftfreq(nperseg, d=1.0 / rate_hz)
    return Windows(
        f_hz=f,
        psd=np.array(psds),
        band_var=np.array(bvs),
        rotor_hz=np.array(rhs) if rhs else None,
        rate_hz=rate_hz,
        nperseg=nperseg,
    )


#: Fewest windows a throttle band is analysed with (its averaged PSD has ν ≈ 2·K·(overlap
#: factor) degrees of freedom; below 4 windows the χ² line threshold exceeds 8× the baseline).
MIN_BAND_WINDOWS = 4


def band_counts(band_var: np.ndarray, edges: np.ndarray) -> list[int]:
    """Windows per band for the half-open bands of ``edges`` (the last one closed), as the band
    loop of :func:`_analyse` selects them."""
    if len(edges) < 2:
        return [int(band_var.size)]
    return [
        int(((band_var >= edges[i]) & ((band_var < edges[i + 1]) | (i == len(edges) - 2))).sum())
        for i in range(len(edges) - 1)
    ]


# ------------------------------------------------------------------ lines
def _baseline(p: np.ndarray, half_bins: int) -> np.ndarray:
    """Running median of log PSD over ±half_bins (robust to the lines themselves)."""
    lp = np.log(np.maximum(p, 1e-300))
    return np.exp(median_filter(lp, size=2 * half_bins + 1, mode="nearest")) / _MEDIAN_LOG_BIAS


#: E[log χ²₂/2] = −γ: the median of log periodogram bins sits below log of the mean; for an
#: average of K windows the bias shrinks. A running median of the *averaged* log PSD (ν ≥ 20)
#: is within ~5 % of the mean level: taken as 1 (documented bias, not a tuned factor).
_MEDIAN_LOG_BIAS = 1.0


@dataclass
class Peak:
    axis: int
    f_hz: float
    power: float  # (unit)² (line power = mean square)
    power_se: float
    psd_peak: float
    ratio: float


def _hann_capture(d: float, k_lo: int, k_hi: int, n: int = 4096) -> float:
    """Fraction of a tone's windowed power (Hann, offset ``d`` bins from bin 0) in bins k_lo..k_hi-1."""
    w = signal.windows.hann(n, sym=False)
    t = np.arange(n)
    tone = w * np.exp(2j * np.pi * (64 + d) * t / n)
    X = np.abs(np.fft.fft(tone)) ** 2
    tot = X.sum()
    return float(X[64 + k_lo : 64 + k_hi].sum() / tot)


def find_peaks(f, pbar, pwin, k_windows: int, *, fmin: float, fmax: float, df_res: float) -> list[Peak]:
    """Peaks of the band-averaged PSD ``pbar`` (M, 3) above the χ² threshold."""
    nu = dof(k_windows)
    sel = (f >= fmin) & (f <= fmax)
    m = int(sel.sum())
    if m < 10:
        return []
    thr = stats.chi2.ppf(1.0 - 0.001 / m, nu) / nu
    df = f[1] - f[0]
    half = max(5, int(round(15.0 / df)))
    peaks = []
    for ax in range(3):
        p = pbar[:, ax]
        base = _baseline(p, half)
        ratio = p / base
        cand = np.nonzero(sel & (ratio > thr))[0]
        # local maxima only, merge neighbours
        taken = []
        for i in cand:
            if i <= 0 or i >= f.size - 1:
                continue
            if p[i] < p[i - 1] or p[i] < p[i + 1]:
                continue
            if taken and i - taken[-1] <= 2:
                if p[i] > p[taken[-1]]:
                    taken[-1] = i
                continue
            taken.append(i)
        for i in taken:
            a, b, c = np.log(p[i - 1]), np.log(p[i]), np.log(p[i + 1])
            den = a - 2 * b + c
            d = 0.5 * (a - c) / den if den < 0 else 0.0
            fi = f[i] + float(np.clip(d, -0.5, 0.5)) * df
            lo, hi = max(i - 2, 0), min(i + 3, f.size)
            # Hann leakage: fraction of a tone's power at offset d bins that lands in bins
            # i-2..i+2 (|W(k - d)|², W the Hann kernel); the line power is divided by it
            cap = _hann_capture(float(np.clip(d, -0.5, 0.5)), lo - i, hi - i)
            exc_w = np.clip(pwin[:, lo:hi, ax] - base[lo:hi][None, :], 0.0, None).sum(axis=1) * df / cap  # per window
            pw = float(np.clip(p[lo:hi] - base[lo:hi], 0.0, None).sum() * df / cap)
            k_eff = max(nu / 2.0, 1.0)
            se_spread = float(np.std(exc_w, ddof=1) / math.sqrt(k_eff)) if exc_w.size > 1 else float("nan")
            # the baseline (noise) power under the line is itself a χ²_ν estimate: SE = P_b·√(2/ν)
            se_base = float(base[lo:hi].sum() * df / cap * math.sqrt(2.0 / nu))
            se = math.hypot(se_spread, se_base)
            peaks.append(Peak(ax, float(fi), pw, se, float(p[i]), float(ratio[i])))
    return peaks
