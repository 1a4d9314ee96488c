"""Energy bands: where a flight's vibration power is when a line wanders inside each window.

A motor line whose frequency follows a throttle that moves within the 1-s analysis window is
smeared over tens of Hz: no single bin stands out, the narrow-line detector of
:mod:`gyrocore.flight.vibration` misses it, and a weaker fixed line is reported instead although the
smeared band carries most of the power. This module finds the bands by their *energy*.

Method, per axis, on an averaged PSD S(f) of K windows (ν ≈ 2K/(1 + 2ρ²) degrees of freedom,
:func:`gyrocore.flight.spectra.dof`, handed in by the caller: this module imports nothing of
the vibration analysis, which calls it):

1. Narrow features out: a running median of log S over :data:`MEDIAN_BINS` = 11 bins. A median
   of length L removes any feature narrower than (L + 1)/2 = 6 bins: a line (a Hann main lobe
   is 4 bins wide) goes, a band wider than 6 bins stays with its edges (a median keeps monotone
   edges); then a running mean of the same length, so the ripple of a periodically swept line
   (a comb with dips 10× deep every few Hz) averages to the band's level (a symmetric kernel
   keeps a band's half-height crossings in place). NaN bins (notch holes of undone filters) are
   bridged log-linearly for this step only.
2. Candidates: the local maxima of the smoothed spectrum S̃ (``scipy.signal.find_peaks``) with
   their prominence; a band must stand at least :data:`MIN_PEAK_TO_BASE` = 2× (3 dB) above the
   higher of its two bases (the minima that separate it from higher peaks or the spectrum's
   ends), so a slope or a ripple of the broadband is not a band.
3. Edges: where S̃ crosses half the prominence above that base (``scipy.signal.peak_widths``,
   ``rel_height=0.5``): the band's full width at half its height above the floor (``edges_hz``,
   ``width_hz``). For a flat-top band (a line sweeping at a steady rate) blurred by any
   symmetric kernel (the window, the sweep's own instantaneous bandwidth √|df/dt|) the
   half-height crossings stay at the true edges. Extent: where S̃ crosses
   :data:`EXTENT_HEIGHT` = 10 % of that height (−10 dB; ``extent_hz``): the span that holds the
   band's energy, also when its density is not flat (a line that spends more time at low
   throttle: the whole flight's band of a line sweeping several throttle bands is a staircase
   that a half-height cut would split). Two candidates' extents that overlap are cut at S̃'s
   minimum between their peaks; a candidate whose peak lies inside a stronger band's extent is
   part of it.
4. Energy: power P = Σ S(f_k)·Δf over the bins whose centres lie inside the extent (the
   unsmoothed PSD: any line inside the band is part of its energy); the centre is the
   power-weighted mean frequency Σ f S / Σ S over the extent (for a constant-amplitude line of
   wandering frequency: its window-weighted mean instantaneous frequency); the peak is S̃'s
   maximum. The share is P over the extent's part of the rms span (40 Hz to the
   reconstruction's reliable limit, the span of ``rms_above_40hz_rad_s``) divided by the power
   of that span: shares of disjoint bands add up to at most 1. A band reaching above the
   reliable limit says how much of its power lies there.
5. Significance: the excess Σ (S − base)·Δf against its standard error
   S̄·Δf·√(2·C·n/ν) (n bins; C = 1 + 2·(4/9) + 2·(1/36) = 1.944 the variance inflation of a sum
   of adjacent Hann-periodogram bins, whose white-noise correlations are (2/3)² and (1/6)²) must
   reach the normal quantile at 1 − 0.001/M (Bonferroni over the M bins searched, as the lines).

Link to throttle: the whole-flight bands (the mean PSD over every airborne window) are matched,
in each throttle band, to the band on the same axis that overlaps them most; the centres
against the bands' median command give the law f = a + b·u (Theil–Sen, robust to a band matched
to another feature, with its 95 % slope interval), ``follows`` = ``throttle`` when the centre
moves by more than 3 resolutions over the bands and the slope interval excludes 0, ``erpm``
(with its harmonic) when a rotor-speed column exists and centre / rotor Hz is within 0.1 of an
integer, else ``fixed``; a centre that falls with throttle is folded from above the logged
Nyquist (``aliased``), as for lines.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
from scipy import signal, stats
from scipy.ndimage import median_filter, uniform_filter1d

from gyrocore.data.jsonable import to_jsonable

__all__ = [
    "EXTENT_HEIGHT",
    "HANN_SUM_VARIANCE_FACTOR",
    "MEDIAN_BINS",
    "MIN_PEAK_TO_BASE",
    "attach",
    "band_interval",
    "dominant_vibration",
    "find_bands",
    "link_bands",
]

#: Running-median (then running-mean) length, bins: removes features narrower than 6 bins (a line), keeps bands.
MEDIAN_BINS = 11
#: A band's smoothed peak over the higher of its bases (3 dB).
MIN_PEAK_TO_BASE = 2.0
#: The band's extent (where its power is integrated): where S̃ stands above this fraction of the
#: band's height over its floor (−10 dB).
EXTENT_HEIGHT = 0.1
#: Var(Σ_k Ŝ_k)/(n·Var Ŝ) for a run of adjacent Hann-periodogram bins of white noise: the bin
#: correlations are |Σw²e^{-2πik n/N}|²/(Σw²)² = (1/4 ÷ 3/8)² = 4/9 at lag 1 and
#: (1/16 ÷ 3/8)² = 1/36 at lag 2, 0 beyond.
HANN_SUM_VARIANCE_FACTOR = 1.0 + 2.0 * (4.0 / 9.0) + 2.0 * (1.0 / 36.0)
AXES = ("x", "y", "z")
#: False-alarm level of the band test over the bins searched (Bonferroni), as the line detector's.
ALPHA = 0.001


def _smooth(x: np.ndarray) -> np.ndarray | None:
    ok = np.isfinite(x) & (x > 0)
    if ok.sum() < 2 * MEDIAN_BINS:
        return None
    lx = np.interp(np.arange(x.size), np.flatnonzero(ok), np.log(x[ok]))
    m = np.exp(median_filter(lx, size=MEDIAN_BINS, mode="nearest"))
    # then a running mean of the same length: the ripple of a periodically swept line (a comb
    # with dips 10x deep every few Hz) averages to the band's level; a symmetric kernel keeps the
    # half-height crossing of a band edge in place
    return uniform_filter1d(m, size=MEDIAN_BINS, mode="nearest")


def _bands_one_axis(
    f: np.ndarray, s: np.ndarray, *, nu: float, search: np.ndarray, rms_mask: np.ndarray, reliable_hz: float, axis: str
) -> list[dict]:
    df = float(f[1] - f[0])
    idx = np.flatnonzero(search)
    if idx.size < 3 * MEDIAN_BINS:
        return []
    x = s[idx]
    sm = _smooth(x)
    if sm is None:
        return []
    peaks, props = signal.find_peaks(sm, prominence=0.0)
    if not peaks.size:
        return []
    prom = props["prominences"]
    base = sm[peaks] - prom
    keep = sm[peaks] >= MIN_PEAK_TO_BASE * np.maximum(base, 1e-300)
    if not keep.any():
        return []
    peaks, prom = peaks[keep], prom[keep]
    lb, rb = props["left_bases"][keep], props["right_bases"][keep]
    _, _, lo_ips, hi_ips = signal.peak_widths(sm, peaks, rel_height=0.5, prominence_data=(prom, lb, rb))
    _, _, lo_ext, hi_ext = signal.peak_widths(sm, peaks, rel_height=1.0 - EXTENT_HEIGHT, prominence_data=(prom, lb, rb))
    total = float(np.nansum(s[rms_mask]) * df)
    med = float(np.nanmedian(s[rms_mask])) if rms_mask.any() else float("nan")
    z_thr = float(stats.norm.isf(ALPHA / idx.size))
    out = []
    order = np.argsort(-prom)
    taken: list[tuple[float, float]] = []
    for j in order:
        lo, hi = float(lo_ext[j]), float(hi_ext[j])
        # two candidates' extents overlapping (a shoulder): cut at S̃'s minimum between the peaks
        for a, b in taken:
            if lo < b and hi > a:
                if peaks[j] > b:
                    lo = max(lo, float(np.argmin(sm[int(b) : peaks[j] + 1]) + int(b)))
                elif peaks[j] < a:
                    hi = min(hi, float(np.argmin(sm[peaks[j] : math.ceil(a) + 1]) + peaks[j]))
                else:
                    lo = hi  # its peak inside a stronger band: part of it
        if hi - lo < 1.0:
            continue
        k = np.arange(math.ceil(lo), math.floor(hi) + 1)
        sk = s[idx[k]]
        fin = np.isfinite(sk)
        if fin.sum() < 2:
            continue
        fk = f[idx[k]]
        pw = float(np.sum(sk[fin]) * df)
        b0 = float(sm[peaks[j]] - prom[j])
        excess = float(np.sum(sk[fin] - b0) * df)
        se = float(np.mean(sk[fin]) * df * math.sqrt(2.0 * HANN_SUM_VARIANCE_FACTOR * fin.sum() / nu))
        if not excess > z_thr * se:
            continue
        taken.append((lo, hi))
        in_rms = rms_mask[idx[k]] & fin
        pw_rms = float(np.sum(sk[in_rms]) * df)
        f0 = float(f[idx[0]])
        e_lo, e_hi = max(float(lo_ips[j]), lo), min(float(hi_ips[j]), hi)
        out.append(
            {
                "axis": axis,
                "peak_hz": float(f[idx[peaks[j]]]),
                "centre_hz": float(np.sum(fk[fin] * sk[fin]) / np.sum(sk[fin])),
                "edges_hz": [f0 + e_lo * df, f0 + e_hi * df],
                "width_hz": (e_hi - e_lo) * df,
                "extent_hz": [f0 + lo * df, f0 + hi * df],
                "power_rad2_s2": pw,
                "rms_rad_s": math.sqrt(pw),
                "share_of_power_above_40hz": pw_rms / total if total > 0 else float("nan"),
                "power_above_reliable_fraction": float(1.0 - pw_rms / pw) if pw > 0 else 0.0,
                "level_reliable": bool(f0 + hi * df < reliable_hz),
                "peak_over_floor": float(sm[peaks[j]] / b0) if b0 > 0 else float("inf"),
                "peak_over_median_psd": float(sm[peaks[j]] / med) if med > 0 else float("nan"),
                "excess_z": excess / se if se > 0 else float("inf"),
            }
        )
    return out


def _order_key(b: dict):
    return (
        -b["share_of_power_above_40hz"] if np.isfinite(b["share_of_power_above_40hz"]) else 0.0,
        -b["power_rad2_s2"],
    )


def find_bands(
    f_hz: np.ndarray, psd: np.ndarray, *, nu: float, fmin_hz: float, reliable_below_hz: float, rms_lo_hz: float = 40.0
) -> list[dict]:
    """Energy bands of an averaged PSD (see the module docstring), all axes, ordered by their share.

    Parameters
    ----------
    f_hz : ndarray (M,)
        Frequencies, Hz (uniform grid).
    psd : ndarray (M, 3)
        Averaged one-sided PSD per axis, (rad/s)²/Hz (NaN: bins with no value).
    nu : float
        Degrees of freedom of the averaged PSD (ν ≈ 2K/(1 + 2ρ²) for K windows).
    fmin_hz : float
        Lowest frequency searched, Hz.
    reliable_below_hz : float
        Upper limit of the rms span (the reconstruction's reliable limit); bands are searched up
        to two bins below Nyquist and flagged ``level_reliable`` false beyond this limit.
    rms_lo_hz : float
        Lower limit of the rms span, Hz (40: ``rms_above_40hz_rad_s``).

    Returns
    -------
    list of dict
        ``axis``, ``peak_hz``, ``centre_hz`` (over the extent), ``edges_hz`` [lo, hi] (half
        height), ``width_hz``, ``extent_hz`` (10 % height), ``power_rad2_s2`` (over the extent),
        ``rms_rad_s``, ``share_of_power_above_40hz`` (the extent's part of the rms span over that
        span's power), ``power_above_reliable_fraction``,
        ``level_reliable``, ``peak_over_floor``, ``peak_over_median_psd`` (S̃ at the peak over the
        median PSD of the rms span), ``excess_z``; ordered by share, then power (largest first).
    """
    f = np.asarray(f_hz, float)
    df = float(f[1] - f[0])
    search = (f >= fmin_hz) & (f <= f[-1] - 2 * df)
    rms_mask = (f >= rms_lo_hz) & (f < reliable_below_hz + 0.5 * df)
    out = []
    for j, a in enumerate(AXES):
        out += _bands_one_axis(
            f,
            np.asarray(psd[:, j], float),
            nu=nu,
            search=search,
            rms_mask=rms_mask,
            reliable_hz=reliable_below_hz,
            axis=a,
        )
    out.sort(key=_order_key)
    return out


def band_interval(
    f_hz: np.ndarray,
    psd_windows: np.ndarray,
    axis: int,
    edges_hz: Sequence[float],
    *,
    rms_lo_hz: float,
    reliable_below_hz: float,
    k_eff: float,
) -> dict:
    """Standard errors of a band's power, share and centre from the spread of the per-window values.

    ``psd_windows`` (K, M, 3): the windows' PSDs; ``edges_hz``: the span integrated (the
    extent). Share s = Σ_k N_k / Σ_k D_k (N: band power in
    the rms span, D: power of the span) and centre c = Σ_k Σ f S / Σ_k Σ S are ratio estimators:
    delta-method SE √(Var(N − sD)/K_eff)/D̄; the power B̄ (mean of the windows' band powers) has
    SE sd(B)/√K_eff; ``k_eff`` = ν/2 (the overlapping windows are not independent:
    ν/2 = K/(1 + 2ρ²) equivalent windows).
    """
    f = np.asarray(f_hz, float)
    df = float(f[1] - f[0])
    P = np.asarray(psd_windows[:, :, axis], float)
    K = P.shape[0]
    inb = (f >= edges_hz[0]) & (f <= edges_hz[1])
    span = (f >= rms_lo_hz) & (f < reliable_below_hz + 0.5 * df)
    N = np.nansum(P[:, inb & span], axis=1) * df
    D = np.nansum(P[:, span], axis=1) * df
    B = np.nansum(P[:, inb], axis=1) * df
    C = np.nansum(P[:, inb] * f[None, inb], axis=1) * df
    k_eff = max(float(k_eff), 1.0)
    s = N.sum() / D.sum() if D.sum() > 0 else float("nan")
    c = C.sum() / B.sum() if B.sum() > 0 else float("nan")
    if K < 2:
        return {
            "power": float(B.mean()),
            "power_se": float("nan"),
            "share": s,
            "share_se": float("nan"),
            "centre_hz": c,
            "centre_se_hz": float("nan"),
        }
    se_s = float(np.std(N - s * D, ddof=1) / math.sqrt(k_eff) / D.mean()) if D.mean() > 0 else float("nan")
    se_c = float(np.std(C - c * B, ddof=1) / math.sqrt(k_eff) / B.mean()) if B.mean() > 0 else float("nan")
    return {
        "power": float(B.mean()),
        "power_se": float(np.std(B, ddof=1) / math.sqrt(k_eff)),
        "share": float(s),
        "share_se": se_s,
        "centre_hz": float(c),
        "centre_se_hz": se_c,
    }


def link_bands(
    flight: list[dict],
    per_band: list[list[dict]],
    band_rows: list[dict],
    *,
    rate_hz: float,
    resolution_hz: float,
    has_bv: bool,
) -> None:
    """Add ``per_band`` entries and the throttle / eRPM law to each whole-flight band (in place).

    ``per_band[b]``: the bands found in throttle band b; ``band_rows[b]``: that band's row
    (``median``, optional ``rotor_hz_median``); ``resolution_hz``: the frequency resolution
    (the window's equivalent noise bandwidth).
    """
    res = float(resolution_hz)
    for e in flight:
        lo, hi = e["extent_hz"]
        rows = []
        for bi, bands in enumerate(per_band):
            best, ov_best = None, 0.0
            for b in bands:
                if b["axis"] != e["axis"]:
                    continue
                ov = min(hi, b["extent_hz"][1]) - max(lo, b["extent_hz"][0])
                if ov > ov_best:
                    best, ov_best = b, ov
            if best is not None:
                rows.append(
                    {
                        "band": bi,
                        "throttle_median": float(band_rows[bi]["median"]),
                        "centre_hz": best["centre_hz"],
                        "peak_hz": best["peak_hz"],
                        "edges_hz": best["edges_hz"],
                        "width_hz": best["width_hz"],
                        "extent_hz": best["extent_hz"],
                        "power_rad2_s2": best["power_rad2_s2"],
                        "share_of_power_above_40hz": best["share_of_power_above_40hz"],
                    }
                )
        e["per_band"] = rows
        e["follows"] = None if not has_bv else "fixed"
        if not has_bv or len(rows) < 3:
            if has_bv and len(rows) < 3:
                e["law_note"] = f"found in {len(rows)} throttle band(s): no law"
                e["follows"] = None
            continue
        u = np.array([r["throttle_median"] for r in rows])
        c = np.array([r["centre_hz"] for r in rows])
        if np.ptp(u) <= 0:
            continue
        # Theil-Sen (median of pairwise slopes): a throttle band whose overlap match is another
        # feature (a folded line at high throttle) does not drag the law; 95 % interval of the slope
        slope, icpt, s_lo, s_hi = stats.theilslopes(c, u, alpha=0.95)
        slope, icpt = float(slope), float(icpt)
        e["law"] = {
            "kind": "centre = hz_at_zero + hz_per_unit * band variable (Theil-Sen)",
            "hz_at_zero": icpt,
            "hz_per_unit": slope,
            "hz_per_unit_interval": [float(s_lo), float(s_hi)],
        }
        moving = abs(slope) * np.ptp(u) > 3 * res and not (s_lo <= 0.0 <= s_hi)
        if moving:
            e["follows"] = "throttle"
            e["aliased"] = bool(slope < 0)
            if slope < 0:
                e["note"] = "centre falls as throttle rises: folded from above the logged Nyquist"
            rh = np.array([band_rows[r["band"]].get("rotor_hz_median", np.nan) for r in rows], float)
            if np.isfinite(rh).any():
                fu = c if slope > 0 else rate_hz - c
                h = float(np.nanmedian(fu / rh))
                if np.isfinite(h) and round(h) >= 1 and abs(h - round(h)) < 0.1:
                    e["follows"] = "erpm"
                    e["harmonic"] = round(h)


def dominant_vibration(bands: list[dict], lines: list[dict]) -> dict:
    """Per axis, the strongest vibration by power in the rms span: the axis's first energy band
    (its power below the reliable limit), or the strongest narrow line outside every band of that
    axis (power A²/2; a line above the reliable limit counts 0) when that line carries more."""
    out = {}
    for a in AXES:
        bs = [b for b in bands if b["axis"] == a]
        ls = [
            ln
            for ln in lines
            if ln["axis"] == a and not any(b["extent_hz"][0] <= ln["frequency_hz"] <= b["extent_hz"][1] for b in bs)
        ]
        cand = []
        if bs:
            b = bs[0]
            cand.append(
                (
                    (b["power_rad2_s2"] * (1.0 - b["power_above_reliable_fraction"]), b["power_rad2_s2"]),
                    {
                        "kind": "band",
                        "frequency_hz": b["centre_hz"],
                        "edges_hz": b["edges_hz"],
                        "extent_hz": b["extent_hz"],
                        "level_reliable": b["level_reliable"],
                        "power_rad2_s2": b["power_rad2_s2"],
                        "share_of_power_above_40hz": b["share_of_power_above_40hz"],
                    },
                )
            )
        for ln in ls:
            p = ln["amplitude_rad_s"] ** 2 / 2.0
            rel = bool(ln.get("level_reliable", True))
            cand.append(
                (
                    (p if rel else 0.0, p),
                    {
                        "kind": "line",
                        "frequency_hz": ln["frequency_hz"],
                        "power_rad2_s2": p,
                        "follows": ln.get("follows"),
                        "level_reliable": rel,
                    },
                )
            )
        if cand:
            out[a] = max(cand, key=lambda c: c[0])[1]
    return out


def attach(
    f_hz: np.ndarray,
    psd_windows: np.ndarray,
    mean_psd: np.ndarray,
    band_psd: Sequence[np.ndarray],
    band_rows: list[dict],
    lines: list[dict],
    *,
    fmin_hz: float,
    reliable_below_hz: float,
    rate_hz: float,
    has_bv: bool,
    dof: Callable[[int], float],
    resolution_hz: float,
    band_windows: Sequence[np.ndarray] | None = None,
) -> tuple[list[dict], dict]:
    """The energy bands of an analysis: whole flight (``mean_psd`` over the K windows of
    ``psd_windows`` (K, M, 3)) with power/share/centre standard errors and their throttle law, and
    per throttle band (``band_psd[b]``, written into ``band_rows[b]["energy_bands"]``; with
    ``band_windows[b]``, the boolean (K,) selection of that band's windows, their standard errors
    too). ``dof(K)``: the degrees of freedom of an average of K windows
    (:func:`gyrocore.flight.spectra.dof`); ``resolution_hz``: the window's equivalent noise
    bandwidth. Returns the whole-flight list and :func:`dominant_vibration`."""
    f = np.asarray(f_hz, float)
    K = int(psd_windows.shape[0])
    flight = find_bands(f, mean_psd, nu=dof(max(K, 1)), fmin_hz=fmin_hz, reliable_below_hz=reliable_below_hz)
    per = []
    for row, pb in zip(band_rows, band_psd):
        bl = find_bands(
            f, pb, nu=dof(max(int(row["n_windows"]), 1)), fmin_hz=fmin_hz, reliable_below_hz=reliable_below_hz
        )
        row["energy_bands"] = bl
        per.append(bl)
    if band_windows is not None:
        for bl, sel in zip(per, band_windows):
            pw_sel = psd_windows[sel] if bl else None  # one copy of the band's windows, not one per energy band
            for e in bl:
                iv = band_interval(
                    f,
                    pw_sel,
                    AXES.index(e["axis"]),
                    e["extent_hz"],
                    rms_lo_hz=40.0,
                    reliable_below_hz=reliable_below_hz,
                    k_eff=dof(int(sel.sum())) / 2.0,
                )
                e.update(power_se=iv["power_se"], share_se=iv["share_se"], centre_se_hz=iv["centre_se_hz"])
    for e in flight:
        iv = band_interval(
            f,
            psd_windows,
            AXES.index(e["axis"]),
            e["extent_hz"],
            rms_lo_hz=40.0,
            reliable_below_hz=reliable_below_hz,
            k_eff=dof(K) / 2.0,
        )
        e.update(power_se=iv["power_se"], share_se=iv["share_se"], centre_se_hz=iv["centre_se_hz"])
        lo, hi = e["extent_hz"]
        e["lines_inside"] = [
            {"frequency_hz": ln["frequency_hz"], "follows": ln["follows"], "amplitude_rad_s": ln["amplitude_rad_s"]}
            for ln in lines
            if ln["axis"] == e["axis"] and lo <= ln["frequency_hz"] <= hi
        ]
    if len(band_rows) > 1:
        link_bands(flight, per, band_rows, rate_hz=rate_hz, resolution_hz=resolution_hz, has_bv=has_bv)
    else:
        for e in flight:
            e["follows"] = None
            e["law_note"] = "one throttle band: no law"
    # non-finite floats → None: the spec is written with allow_nan=False
    for row in band_rows:
        row["energy_bands"] = to_jsonable(row["energy_bands"])
    return to_jsonable(flight), to_jsonable(dominant_vibration(flight, lines))
