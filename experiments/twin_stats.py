"""The statistics the twin compares between a real recording and its replicas (per-window
error, autocorrelation, PSD bands, tails, Allan deviation), laid out once per reference."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal

from .twin_reference import Reference, _quat_R
from gyrocore.attitude import integrate_gyro

#: Window of the per-window statistics, s.
WINDOW_S = 1.0
#: Lags of the autocorrelation statistic.
ACF_LAGS = 5
#: Welch segment length and number of log-spaced bands of the PSD statistic.
PSD_NPERSEG = 256
PSD_BANDS = 16
#: Tail statistic: the fraction of samples beyond this many robust σ.
TAIL_SIGMA = 4.0


def _span_concat(x: np.ndarray, spans) -> np.ndarray:
    return np.concatenate([x[a:b] - x[a:b].mean(axis=0) for a, b in spans])


def _pooled_adev(e: np.ndarray, spans, m_list: np.ndarray, rate: float) -> np.ndarray:
    """Overlapping ADEV (3, J) pooled over spans: σ²(τ) = Σ (x_{k+2m} − 2x_{k+m} + x_k)² / (2τ²·count)."""
    num = np.zeros((3, m_list.size))
    cnt = np.zeros(m_list.size)
    tau0 = 1.0 / rate
    for a, b in spans:
        x = np.concatenate([np.zeros((1, 3)), np.cumsum(e[a:b], axis=0) * tau0])  # phase, rad
        L = x.shape[0]
        for j, m in enumerate(m_list):
            if L <= 2 * m:
                continue
            d = x[2 * m :] - 2 * x[m:-m] + x[: -2 * m]
            num[:, j] += np.sum(d * d, axis=0)
            cnt[j] += d.shape[0]
    tau = m_list * tau0
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(num / (2.0 * tau[None, :] ** 2 * cnt[None, :]))


@dataclass(frozen=True, eq=False)
class StatLayout:
    """The bins of each statistic, fixed by the real recording so replicas share them."""

    m_list: np.ndarray
    nperseg: int
    band_edges_hz: np.ndarray
    window: int
    rate_hz: float
    att_windows: tuple | None = None  # (a, b) index arrays of the attitude windows

    def x(self, name: str) -> tuple[np.ndarray, str]:
        if name == "adev":
            return self.m_list / self.rate_hz, "τ, s"
        if name == "psd":
            return np.sqrt(self.band_edges_hz[:-1] * self.band_edges_hz[1:]), "frequency, Hz"
        if name == "distribution":
            return np.arange(3), "log10 std | excess kurtosis | P(|e|>4σ)"
        if name == "window_acf":
            return np.arange(1, ACF_LAGS + 1), f"lag, windows of {self.window / self.rate_hz:g} s"
        return np.arange(5), "log10 std | excess kurtosis | acf 1 | acf 2 | acf 3"


def layout_for(ref: Reference, rate_hz: float, n: int) -> StatLayout:
    longest = max(b - a for a, b in ref.spans)
    m_list = 2 ** np.arange(0, 40)
    m_list = m_list[m_list <= longest // 5]
    nperseg = int(min(PSD_NPERSEG, 2 ** int(np.floor(np.log2(longest)))))
    f_lo = rate_hz / nperseg
    edges = np.geomspace(f_lo * 0.999, rate_hz / 2 * 1.0001, PSD_BANDS + 1)
    window = max(2, int(round(WINDOW_S * rate_hz)))
    att = None
    if ref.kind == "attitude":
        q = ref.q_ref_wxyz
        ok = np.all(np.isfinite(q), axis=1)
        L = window
        a = np.arange(0, n - L, L)
        b = a + L
        # whole window tracked (not only its ends): the twin's replay across a gap is interpolated
        bad = np.concatenate([[0], np.cumsum(~ok)])
        keep = (bad[b + 1] - bad[a]) == 0
        att = (a[keep], b[keep])
    return StatLayout(
        m_list=m_list, nperseg=nperseg, band_edges_hz=edges, window=window, rate_hz=rate_hz, att_windows=att
    )


def _acf(series: list[np.ndarray], lags: int) -> np.ndarray:
    """Pooled autocorrelation (3, lags) of per-span series (each (L, 3), mean removed)."""
    num = np.zeros((3, lags))
    den = np.zeros(3)
    for s in series:
        s = s - s.mean(axis=0)
        den += np.sum(s * s, axis=0)
        for k in range(1, lags + 1):
            if s.shape[0] > k:
                num[:, k - 1] += np.sum(s[k:] * s[:-k], axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return num / den[:, None]


def _attitude_windows(gyro: np.ndarray, t: np.ndarray, R_ref, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Window residual (M, 3) rad/s: rotvec((R_aᵀR_b)ᵀ·ΔR̂_{a→b})/T (gyrocore.loop.residual, attitude kind)."""
    qh = integrate_gyro(t, gyro, hold="backward")
    Rh = _quat_R(qh)
    rel_ref = R_ref[a].inv() * R_ref[b]
    rel_hat = Rh[a].inv() * Rh[b]
    return (rel_ref.inv() * rel_hat).as_rotvec() / (t[b] - t[a])[:, None]


def error_statistics(e: np.ndarray, spans, layout: StatLayout, *, att_resid: np.ndarray | None = None) -> dict:
    """The statistics of one error signal: ``{name: ndarray (3, J)}`` (see the module docstring).

    Parameters
    ----------
    e : ndarray, shape (N, 3)
        Error signal, rad/s (measurement − reference rate), valid on ``spans``.
    spans : list of (a, b)
    layout : StatLayout
    att_resid : ndarray, shape (M, 3), optional
        Attitude window residual (attitude references).
    """
    rate = layout.rate_hz
    out: dict[str, np.ndarray] = {}
    out["adev"] = np.log10(_pooled_adev(e, spans, layout.m_list, rate))
    # Welch, averaged over spans by their number of segments
    acc, wsum = None, 0.0
    for a, b in spans:
        if b - a < layout.nperseg:
            continue
        f, P = signal.welch(e[a:b], fs=rate, nperseg=layout.nperseg, axis=0, detrend="constant")
        nseg = 1 + (b - a - layout.nperseg) // (layout.nperseg // 2)
        acc = P * nseg if acc is None else acc + P * nseg
        wsum += nseg
    P = acc / wsum
    idx = np.digitize(f, layout.band_edges_hz) - 1
    bands = np.stack(
        [P[idx == j].mean(axis=0) if np.any(idx == j) else np.full(3, np.nan) for j in range(PSD_BANDS)], axis=1
    )
    out["psd"] = np.log10(bands)
    x = _span_concat(e, spans)
    sd = x.std(axis=0)
    kurt = np.mean(x**4, axis=0) / sd**4 - 3.0
    tail = np.mean(np.abs(x) > TAIL_SIGMA * sd[None, :], axis=0)
    out["distribution"] = np.stack([np.log10(sd), kurt, tail], axis=1)
    W = layout.window
    wins = []
    for a, b in spans:
        k = (b - a) // W
        if k >= 2:
            wins.append(e[a : a + k * W].reshape(k, W, 3).mean(axis=1))
    out["window_acf"] = _acf(wins, ACF_LAGS)
    if att_resid is not None:
        y = att_resid
        s = y.std(axis=0)
        ku = np.mean((y - y.mean(0)) ** 4, axis=0) / s**4 - 3.0
        ac = _acf([y], 3)
        out["attitude_residual"] = np.column_stack([np.log10(s), ku, ac])
    return out
