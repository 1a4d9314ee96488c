"""Identify the vibration a gyro sees in flight: spectra against throttle, broadband level, lines.

Input: any data file (a converted flight log or a simulated hover). What is analysed
(``signal`` of DESIGN.md "Flight logs and vibration"):

* ``raw`` — the gyro before every firmware gyro filter: a logged unfiltered gyro
  (``gyro_prefilter_*`` with ``gyro_prefilter.signal = raw``), a simulated recording (no
  firmware), or a less-filtered / filtered gyro whose *static* firmware filters were undone by
  dividing the spectrum by their known response |H(f)|² (each listed in ``filters_before``
  with ``"undone": true``; ``reconstructed_reliable_below_hz`` says where folded content from
  above the logged Nyquist makes that unreliable);
* ``partly_filtered`` — dynamic filters (dynamic notch, RPM notch, dynamic LPF) cannot be
  undone (their centre moves and is not logged): listed with ``"undone": false``;
* ``filtered`` — ``--no-undo``: the signal as logged.

Estimator (hand-written on top of ``scipy.signal.stft`` because Welch's average hides the
per-window throttle): Hann windows of ``nperseg`` samples, 50 % overlap, one-sided PSD per
window ((rad/s)²/Hz); windows holding a time gap are dropped; the airborne windows are
averaged per throttle band (the band variable: mean motor command, else rc throttle). Averaged
periodograms of K windows with 50 % overlap Hann have ν ≈ 2K/(1 + 2ρ²) degrees of freedom,
ρ = 0.167 the window overlap correlation (Percival & Walden 1993, §6.17), so
νŜ/S ~ χ²_ν: the PSD interval is [νŜ/χ²_ν(0.975), νŜ/χ²_ν(0.025)].

Lines: bins whose PSD exceeds a running-median baseline by the χ²_ν quantile at
1 − 0.001/M (Bonferroni over the M bins searched) are peaks; frequency by parabolic
interpolation of log PSD (resolution: the Hann ENBW 1.5·fs/nperseg); amplitude of the
sinusoid = √(2·P) with P the line power (PSD excess over the baseline summed over ±2 bins ×
Δf), interval from the spread of the per-window line power (mean ± 1.96·SE with
K_eff = ν/2 windows). Lines are linked across throttle bands: the same frequency in most bands
→ ``fixed`` (a frame resonance); a frequency that rises with the band variable → ``throttle``
(or ``erpm`` when a rotor-speed column exists and f/rotor_hz is near an integer harmonic); one
that *falls* with throttle is folded from above the logged Nyquist (``aliased``: true, the
unfolded frequency fs − f given).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy import signal, stats

from gyrocore.errors import GyroInputError
from gyrocore.data.recording import Recording, atomic_write_text
from gyrocore.flight.energy_bands import attach as attach_energy_bands

__all__ = [
    "VibrationResult",
    "analyse",
    "write_spec",
    "read_spec",
    "SPEC_FORMAT_VERSION",
    "undo_response",
    "plot_vibration",
    "synthesize",
    "shaped_params",
    "add_vibration",
    "fidelity",
    "spec_band",
]

AXES = ("x", "y", "z")
#: 1.1: ``energy_bands`` (whole flight, and per throttle band inside ``bands``; gyrocore.flight.energy_bands)
SPEC_FORMAT_VERSION = "1.1"
DEG = math.pi / 180.0
#: Equivalent-dof correlation of 50 %-overlapped Hann windows (Percival & Walden 1993, Table 292).
RHO_HANN_50 = 0.167
#: Hann window equivalent noise bandwidth, bins.
ENBW_HANN = 1.5
HIGHPASS_HZ = 40.0
#: Bins where the undone filters' |H|² is below −20 dB (around a notch) are not reconstructed:
#: dividing by it would amplify the logged noise floor and quantisation 100-fold.
H2_FLOOR = 1e-2


def _dof(k: int) -> float:
    return 2.0 * k / (1.0 + 2.0 * RHO_HANN_50**2)


# ------------------------------------------------------------------ signal choice
def _stage_filter(stage: dict, loop_scale: float):
    """SosFilter of a static firmware stage (gyrocore.flight.filters), at its nominal rate scaled to the measured clock."""
    from . import filters as F

    kind, fc, rate = stage["kind"], float(stage["cutoff_hz"]), float(stage["rate_hz"])
    if kind == "notch":
        flt = F.biquad_notch(fc, rate, q=float(stage["q"]))
    elif kind in ("pt1", "pt2", "pt3", "biquad"):
        flt = F.make_filter(kind, fc, rate)
    else:
        return None
    return F.SosFilter(flt.sos, rate_hz=rate * loop_scale, name=flt.name, cutoff_hz=fc)


def undo_response(
    stages: Sequence[dict], f_hz: np.ndarray, *, loop_scale: float = 1.0, log_rate_hz: float | None = None
):
    """|H(f)|² of the undoable (static) stages, the stages that cannot be undone, and the reliable band.

    Parameters
    ----------
    stages : list of dict
        Firmware stages (``gyrocore.readers.blackbox.FilterStage.to_dict``).
    f_hz : ndarray (M,)
        Frequencies, Hz.
    loop_scale : float
        Measured / nominal loop rate (the firmware designs its filters for the nominal loop
        period; they run on the real clock).
    log_rate_hz : float
        Logged rate: content at f may have folded from fs − f; reconstruction is called
        reliable below the first f where |H(fs − f)|² / |H(f)|² > 0.25 (an image of equal raw
        power would bias the undone PSD by more than 25 %) or |H(f)|² < 1e-3 (−30 dB).

    Returns
    -------
    H2 : ndarray (M,), done : list of dict, not_done : list of dict, reliable_below_hz : float
    """
    H2 = np.ones_like(f_hz, dtype=float)
    done, not_done, flts = [], [], []
    for s in stages:
        flt = None if s.get("dynamic") else _stage_filter(s, loop_scale)
        if flt is None:
            not_done.append(dict(s, undone=False))
            continue
        flts.append(flt)
        H2 *= flt.response(f_hz).magnitude ** 2
        done.append(dict(s, undone=True))
    reliable = float(f_hz[-1]) if f_hz.size else float("nan")
    # folding: only where a filter ran faster than the log (decimation without anti-aliasing);
    # a filter at the logged rate has no image (its response is periodic in that rate)
    if flts and log_rate_hz and any(flt.rate_hz > 1.01 * log_rate_hz for flt in flts):
        img = np.clip(log_rate_hz - f_hz, 0.0, None)
        Himg = np.ones_like(f_hz)
        for flt in flts:
            Himg *= flt.response(img).magnitude ** 2
        bad = (Himg / np.maximum(H2, 1e-300) > 0.25) & (H2 >= H2_FLOOR)
        bad &= f_hz > 0
        if bad.any():
            reliable = float(f_hz[np.argmax(bad)])
    return H2, done, not_done, reliable


@dataclass(frozen=True)
class _Signal:
    gyro: np.ndarray
    kind: str  # raw / partly_filtered / filtered
    source: str
    stages_before: list
    undo: bool


#: Metadata a multi-log blackbox file carries per log when its logs differ (gyrocore.readers.blackbox):
#: one spectrum cannot undo two filter chains, mix two debug signals or two log rates.
_PER_LOG_KEYS = {
    "gyro_filters": "gyro filters",
    "gyro_prefilter": "less-filtered gyro signal",
    "debug_mode": "debug mode",
    "log_rate_nominal_hz": "log rate",
}


def _describe_setting(key: str, value) -> str:
    if key == "gyro_filters" and isinstance(value, str):
        try:
            return " + ".join(f"{f['kind']} {f['cutoff_hz']:g} Hz" for f in json.loads(value)) or "none"
        except (ValueError, KeyError, TypeError):
            pass
    return str(value)[:60]


def _check_logs_alike(rec: Recording, t_from_s: float | None, t_to_s: float | None) -> None:
    """One ``error:`` line when the analysed time span covers logs of one file flown with
    different gyro filters, debug signal or log rate (the blackbox reader joins the logs of a
    file end to end and keeps each log's settings in ``<key>_per_log``): the spectrum would
    undo the first log's filters on all of them."""
    keys = [k for k in _PER_LOG_KEYS if f"{k}_per_log" in rec.meta]
    if not keys:
        return
    try:
        spans = json.loads(rec.meta.get("logs", "[]"))
    except ValueError:
        spans = []
    lo = -math.inf if t_from_s is None else t_from_s
    hi = math.inf if t_to_s is None else t_to_s
    inside = [int(sp["log"]) for sp in spans if sp["t_end_s"] >= lo and sp["t_start_s"] < hi]
    for k in keys:
        per = json.loads(rec.meta[f"{k}_per_log"])
        vals = {str(i): per.get(str(i)) for i in inside}
        if len(set(json.dumps(v) for v in vals.values())) > 1:
            desc = "; ".join(f"log {i}: {_describe_setting(k, v)}" for i, v in vals.items())
            raise GyroInputError(
                f"the file's logs {', '.join(vals)} were flown with different {_PER_LOG_KEYS[k]} ({desc}): "
                f"one spectrum cannot undo both; analyse one log at a time with --log-index N"
            )


def _choose_signal(rec: Recording, *, use: str, undo: bool) -> _Signal:
    meta = rec.meta
    pre = meta.get("gyro_prefilter")
    have_pre = all(f"gyro_prefilter_{a}_rad_s" in rec.extra for a in AXES)
    fw_chain = json.loads(meta["gyro_filters"]) if "gyro_filters" in meta else None
    if use in ("auto", "prefilter") and have_pre and pre:
        info = json.loads(pre)
        g = np.column_stack([rec.extra[f"gyro_prefilter_{a}_rad_s"] for a in AXES])
        return _Signal(g, info["signal"], info["source"], list(info.get("filters_before", [])), undo)
    if use == "prefilter":
        raise GyroInputError("the recording holds no less-filtered gyro (gyro_prefilter_* columns)")
    if fw_chain is not None:
        return _Signal(
            rec.gyro_rad_s, "filtered", "gyro columns (" + meta.get("gyro_signal", "as flown") + ")", fw_chain, undo
        )
    return _Signal(
        rec.gyro_rad_s, "raw", "gyro columns (no firmware filter metadata: a simulated or raw recording)", [], undo
    )


# ------------------------------------------------------------------ windows
@dataclass(frozen=True)
class _Windows:
    f_hz: np.ndarray  # (M,)
    psd: np.ndarray  # (K, M, 3)   (unit)²/Hz
    band_var: np.ndarray  # (K,) mean of the band variable in each window
    rotor_hz: np.ndarray | None  # (K,) mean rotor frequency, Hz
    rate_hz: float
    nperseg: int


def _windows(t_s, x, band_var, rotor_hz, airborne, *, nperseg: int, rate_hz: float) -> _Windows:
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
    return _Windows(
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


def _band_counts(band_var: np.ndarray, edges: np.ndarray) -> list[int]:
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
    from scipy.ndimage import median_filter

    lp = np.log(np.maximum(p, 1e-300))
    return np.exp(median_filter(lp, size=2 * half_bins + 1, mode="nearest")) / _MEDIAN_LOG_BIAS


#: E[log χ²₂/2] = −γ: the median of log periodogram bins sits below log of the mean; for an
#: average of K windows the bias shrinks. A running median of the *averaged* log PSD (ν ≥ 20)
#: is within ~5 % of the mean level: taken as 1 (documented bias, not a tuned factor).
_MEDIAN_LOG_BIAS = 1.0


@dataclass
class _Peak:
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


def _find_peaks(f, pbar, pwin, k_windows: int, *, fmin: float, fmax: float, df_res: float) -> list[_Peak]:
    """Peaks of the band-averaged PSD ``pbar`` (M, 3) above the χ² threshold."""
    nu = _dof(k_windows)
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
            peaks.append(_Peak(ax, float(fi), pw, se, float(p[i]), float(ratio[i])))
    return peaks


@dataclass(frozen=True)
class VibrationResult:
    """Result of :func:`analyse` (JSON form: :meth:`to_json`, DESIGN.md keys first)."""

    format_version: str
    rate_hz: float
    signal: str
    source: str
    filters_before: list
    reliable_below_hz: float
    rms_above_40hz_rad_s: dict
    rms_above_40hz_interval_rad_s: dict
    rms_band_hz: list
    accel_rms_above_40hz_m_s2: dict | None
    lines: list
    bands: list
    band_variable: str | None
    notes: list
    warnings: list
    f_hz: np.ndarray = field(repr=False)
    band_psd: np.ndarray = field(repr=False)  # (B, M, 3) raw-domain PSD, (rad/s)²/Hz
    band_psd_accel: np.ndarray | None = field(repr=False, default=None)
    mean_psd: np.ndarray = field(repr=False, default=None)  # (M, 3) over all airborne windows
    n_windows: int = 0
    nperseg: int = 0
    energy_bands: list = field(default_factory=list)  # gyrocore.flight.energy_bands, whole flight, by share
    dominant_vibration: dict = field(default_factory=dict)  # per axis: the strongest band or line

    def to_json(self) -> dict:
        return {
            "rate_hz": self.rate_hz,
            "signal": self.signal,
            "filters_before": self.filters_before,
            "rms_above_40hz_rad_s": self.rms_above_40hz_rad_s,
            "lines": self.lines,
            "bands": self.bands,
            "rms_above_40hz_interval_rad_s": self.rms_above_40hz_interval_rad_s,
            "rms_band_hz": self.rms_band_hz,
            "accel_rms_above_40hz_m_s2": self.accel_rms_above_40hz_m_s2,
            "signal_source": self.source,
            "reconstructed_reliable_below_hz": self.reliable_below_hz,
            "band_variable": self.band_variable,
            "frequency_resolution_hz": ENBW_HANN * self.rate_hz / self.nperseg,
            "n_windows": self.n_windows,
            "window_s": self.nperseg / self.rate_hz,
            "notes": self.notes,
            "warnings": self.warnings,
            "format_version": self.format_version,
            "energy_bands": self.energy_bands,
            "dominant_vibration": self.dominant_vibration,
        }


def _band_variable(rec: Recording):
    if "motor_cmd_mean" in rec.extra:
        return rec.extra["motor_cmd_mean"], "motor_cmd_mean (mean motor command, 0-1 of motorOutput)"
    if "throttle" in rec.extra:
        return rec.extra["throttle"], "throttle (rc throttle, 0-1)"
    return None, None


def _rotor_hz(rec: Recording):
    cols = sorted(k for k in rec.extra if k.startswith("rotor_hz_"))
    if not cols:
        return None
    return np.mean([rec.extra[k] for k in cols], axis=0)


def analyse(
    rec: Recording,
    *,
    use: str = "auto",
    undo: bool = True,
    window_s: float = 1.0,
    n_bands: int = 8,
    t_from_s: float | None = None,
    airborne_min_cmd: float = 0.1,
    fmin_hz: float = 40.0,
    t_to_s: float | None = None,
    band_edges: Sequence[float] | None = None,
) -> VibrationResult:
    """Vibration of a recording: PSD per throttle band, broadband RMS above 40 Hz, lines and their laws.

    Parameters
    ----------
    rec : Recording
        A data file (converted flight log or simulated recording).
    use : {"auto", "prefilter", "gyro"}
        Signal: the less-filtered gyro when present (auto), or the gyro columns.
    undo : bool
        Undo the static firmware filters the signal went through (their known response).
    window_s : float
        Hann window length, s (resolution 1.5/window_s Hz).
    n_bands : int
        Throttle bands (equal-count quantiles of the band variable over airborne windows).
    t_from_s, t_to_s : float, optional
        Analyse only t_from_s ≤ t < t_to_s (e.g. after a simulated take-off; one half of a
        flight, to build a spec on one part and compare on the other).
    band_edges : sequence of float, optional
        Throttle band edges (increasing; e.g. another part's ``[b["throttle"][0] for b in
        bands] + [last hi]``) instead of the equal-count quantiles, so two analyses band alike.
    airborne_min_cmd : float
        Airborne = band variable ≥ this (motor command fraction); all samples when the
        recording has no motor/throttle column.
    fmin_hz : float
        Lowest line frequency searched, Hz.
    """
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Mean of empty slice", category=RuntimeWarning)
        return _analyse(
            rec,
            use=use,
            undo=undo,
            window_s=window_s,
            n_bands=n_bands,
            t_from_s=t_from_s,
            airborne_min_cmd=airborne_min_cmd,
            fmin_hz=fmin_hz,
            t_to_s=t_to_s,
            band_edges=band_edges,
        )


def _analyse(
    rec, *, use, undo, window_s, n_bands, t_from_s, airborne_min_cmd, fmin_hz, t_to_s=None, band_edges=None
) -> VibrationResult:
    if use not in ("auto", "prefilter", "gyro"):
        raise GyroInputError(f"signal must be auto, prefilter or gyro, got {use!r}")
    notes, warns = [], []
    _check_logs_alike(rec, t_from_s, t_to_s)
    sig = _choose_signal(rec, use=use, undo=undo)
    t = rec.t_s
    rate = 1.0 / float(np.median(np.diff(t)))
    nper = int(round(window_s * rate))
    if nper < 32:
        raise GyroInputError(f"window of {window_s} s holds {nper} samples at {rate:.0f} Hz; use a longer --window-s")
    nper += nper % 2
    bv, bv_name = _band_variable(rec)
    airborne = np.ones(rec.n, bool)
    if bv is not None:
        airborne &= np.isfinite(bv) & (bv >= airborne_min_cmd)
    if t_from_s is not None:
        airborne &= t >= t_from_s
    if t_to_s is not None:
        airborne &= t < t_to_s
    if t_from_s is not None or t_to_s is not None:
        in_span = np.ones(rec.n, bool)
        if t_from_s is not None:
            in_span &= t >= t_from_s
        if t_to_s is not None:
            in_span &= t < t_to_s
        if not in_span.any():
            raise GyroInputError(f"--t-from-s/--t-to-s select 0 samples; the recording spans t = {t[0]:g}-{t[-1]:g} s")
    if not airborne.any():
        raise GyroInputError(
            "no airborne samples (band variable below the airborne threshold everywhere"
            + (" in the selected time span)" if t_from_s is not None or t_to_s is not None else ")")
        )
    try:
        W = _windows(t, sig.gyro, bv, _rotor_hz(rec), airborne, nperseg=nper, rate_hz=rate)
    except GyroInputError as exc:
        if rec.meta.get("stream") == "batch" and rec.meta.get("batch_window_s"):
            wb = float(rec.meta["batch_window_s"])
            raise GyroInputError(
                f"{exc}: the batch sampler's windows are {wb:.3g} s long; use --window-s "
                f"{math.floor(wb * 0.95 * 100) / 100:g} or less"
            ) from None
        raise
    f = W.f_hz
    # undo the firmware filters in the spectral domain
    loop_scale = 1.0
    if "loop_rate_measured_hz" in rec.meta and "gyro_rate_hz" in rec.meta:
        try:
            ls = float(rec.meta["loop_rate_measured_hz"]) / float(rec.meta["pid_rate_hz"])
            loop_scale = ls if np.isfinite(ls) and 0.5 < ls < 2 else 1.0
        except (KeyError, ValueError):
            loop_scale = 1.0
    kind = sig.kind
    filters_before = [dict(s, undone=False) for s in sig.stages_before]
    H2 = np.ones_like(f)
    reliable = float(f[-1])
    if sig.stages_before and undo:
        H2, done, not_done, reliable = undo_response(sig.stages_before, f, loop_scale=loop_scale, log_rate_hz=rate)
        filters_before = done + not_done
        kind = "raw" if not not_done else "partly_filtered"
        if done:
            notes.append(
                "undone in the spectrum (|H|^2 divided out): "
                + ", ".join(_label(s) for s in done)
                + f"; reliable below {reliable:.0f} Hz (folding from above the logged Nyquist {rate / 2:.0f} Hz)"
            )
        if not_done:
            warns.append(
                "the spectrum has been through "
                + ", ".join(_label(s) for s in not_done)
                + " (dynamic: response not logged, cannot be undone)"
            )
    elif sig.stages_before:
        warns.append(
            "no unfiltered gyro analysed: the spectrum has been through "
            + ", ".join(_label(s) for s in sig.stages_before)
        )
    if sig.kind == "filtered" and "gyro_prefilter" not in rec.meta and sig.stages_before:
        why = [x for x in rec.meta.get("lacks", "").split(" | ") if x.startswith("no unfiltered gyro")]
        warns.append(
            "no unfiltered gyro in the log"
            + (f" ({why[0].split(': ', 1)[1].split(' (')[0]})" if why else "")
            + ": the spectrum has been through "
            + ", ".join(_label(s) for s in sig.stages_before)
            + ("; the static ones are undone in the spectrum" if undo else "")
        )
    psd = W.psd / H2[None, :, None]  # above ``reliable`` kept for the plot/spec, flagged, not integrated
    hole = H2 < H2_FLOOR
    psd[:, hole, :] = np.nan
    if hole.any():
        edges_h = np.flatnonzero(np.diff(np.concatenate([[0], hole.astype(int), [0]])))
        spans = [(float(f[a]), float(f[b - 1])) for a, b in zip(edges_h[::2], edges_h[1::2])]
        notes.append(
            "not reconstructed (undone filters below -20 dB): " + ", ".join(f"{a:.0f}-{b:.0f} Hz" for a, b in spans)
        )
    # accel windows (as logged)
    accel_psd = None
    if rec.accel_m_s2 is not None:
        Wa = _windows(t, rec.accel_m_s2, bv, None, airborne, nperseg=nper, rate_hz=rate)
        accel_psd = Wa.psd
    K = psd.shape[0]
    df = f[1] - f[0]
    hp = (f >= HIGHPASS_HZ) & (f < reliable + 0.5 * df)
    band_hi = float(f[hp][-1]) if hp.any() else float("nan")

    def rms_stats(P, mask):
        pw = np.nansum(P[:, mask, :], axis=1) * df  # (K, 3) per-window band power
        m = pw.mean(axis=0)
        k_eff = max(_dof(P.shape[0]) / 2.0, 1.0)
        se = pw.std(axis=0, ddof=1) / math.sqrt(k_eff) if P.shape[0] > 1 else np.full(3, np.nan)
        lo = np.sqrt(np.clip(m - 1.96 * se, 0, None))
        hi = np.sqrt(m + 1.96 * se)
        return np.sqrt(m), lo, hi

    rms, rlo, rhi = rms_stats(psd, hp)
    arms = None
    if accel_psd is not None:
        am, _, _ = rms_stats(accel_psd, f >= HIGHPASS_HZ)
        arms = {a: float(am[i]) for i, a in enumerate(AXES)}
    # throttle bands
    if band_edges is not None:
        edges = np.asarray(band_edges, float)
        if edges.ndim != 1 or edges.size < 2 or not np.all(np.diff(edges) > 0):
            raise GyroInputError(f"band edges must be an increasing list of at least 2 values, got {list(band_edges)}")
        if bv is None:
            raise GyroInputError("band edges need a motor or throttle column")
    elif bv is not None and np.ptp(W.band_var) > 0.02:
        # equal-count bands, as many as asked for while every band keeps MIN_BAND_WINDOWS
        # windows (a band with fewer is not analysed: on a 17-s flight 8 bands of 3 windows
        # had dropped 18 of 26 windows, and the flight's motor line with them)
        for nb in range(max(1, min(int(n_bands), K // MIN_BAND_WINDOWS)), 0, -1):
            edges = np.unique(np.quantile(W.band_var, np.linspace(0, 1, nb + 1)))
            if min(_band_counts(W.band_var, edges)) >= MIN_BAND_WINDOWS:
                break
        if len(edges) - 1 < n_bands:
            notes.append(
                f"{len(edges) - 1} throttle band(s) instead of {n_bands}: {K} windows of {window_s:g} s, "
                f"each band needs at least {MIN_BAND_WINDOWS}"
            )
    else:
        edges = np.array([W.band_var.min(), W.band_var.max()]) if bv is not None else np.array([0.0, 0.0])
        if bv is not None:
            notes.append("no throttle variation: lines have no throttle law")
        else:
            notes.append("no motor or throttle column: one band, lines have no throttle law")
    band_psd, band_apsd, band_rows, band_sel = [], [], [], []
    dropped: list = []
    for bi in range(len(edges) - 1 if len(edges) > 1 else 1):
        lo_e, hi_e = (edges[bi], edges[bi + 1]) if len(edges) > 1 else (edges[0], edges[0])
        sel = (
            (W.band_var >= lo_e) & ((W.band_var < hi_e) | (bi == len(edges) - 2))
            if len(edges) > 1
            else np.ones(K, bool)
        )
        if sel.sum() < MIN_BAND_WINDOWS:
            dropped.append((float(lo_e), float(hi_e), int(sel.sum())))
            continue
        pb = np.nanmean(psd[sel], axis=0)
        b_rms, b_lo, b_hi = rms_stats(psd[sel], hp)
        row = {
            "throttle": [float(lo_e), float(hi_e)],
            "median": float(np.median(W.band_var[sel])),
            "n_windows": int(sel.sum()),
            "rms_above_40hz_rad_s": {a: float(b_rms[i]) for i, a in enumerate(AXES)},
            "rms_above_40hz_interval_rad_s": {a: [float(b_lo[i]), float(b_hi[i])] for i, a in enumerate(AXES)},
        }
        if W.rotor_hz is not None:
            row["rotor_hz_median"] = float(np.median(W.rotor_hz[sel]))
        if accel_psd is not None:
            pa = np.nanmean(accel_psd[sel], axis=0)
            band_apsd.append(pa)
            am_, _, _ = rms_stats(accel_psd[sel], f >= HIGHPASS_HZ)
            row["accel_rms_above_40hz_m_s2"] = {a: float(am_[i]) for i, a in enumerate(AXES)}
        peaks = _find_peaks(
            f,
            np.nanmean(W.psd[sel], axis=0),
            W.psd[sel],
            int(sel.sum()),
            fmin=fmin_hz,
            fmax=f[-1] - 2 * df,
            df_res=ENBW_HANN * df,
        )
        # line power in the raw domain: scale by 1/|H|² at the line (smooth across ±2 bins)
        kept = []
        for p in peaks:
            g = float(np.interp(p.f_hz, f, H2))
            if g < H2_FLOOR:
                continue
            p.power /= g
            p.power_se /= g
            kept.append(p)
        peaks = kept
        row["_peaks"] = peaks
        band_rows.append(row)
        band_psd.append(pb)
        band_sel.append(sel)
    if dropped:
        notes.append(
            "not analysed (fewer than %d windows): " % MIN_BAND_WINDOWS
            + ", ".join(f"band {a:.3g}-{b:.3g} ({n} windows)" for a, b, n in dropped)
            + ("" if band_rows else "; no band spectra or lines, the rms is over all windows")
        )
    lines = _link_lines(
        band_rows, f, rate, has_bv=bv is not None and len(edges) > 2, rotor=W.rotor_hz is not None, reliable_hz=reliable
    )
    for r in band_rows:
        pk = r.pop("_peaks")
        r["peaks_hz"] = {a: sorted(round(p.f_hz, 1) for p in pk if p.axis == i) for i, a in enumerate(AXES)}
    mean_psd = np.nanmean(psd, axis=0)
    energy, dominant = attach_energy_bands(
        f,
        psd,
        mean_psd,
        band_psd,
        band_rows,
        lines,
        fmin_hz=fmin_hz,
        reliable_below_hz=reliable,
        rate_hz=rate,
        has_bv=bv is not None and len(edges) > 2,
        dof=_dof,
        resolution_hz=ENBW_HANN * df,
        band_windows=band_sel,
    )
    return VibrationResult(
        format_version=SPEC_FORMAT_VERSION,
        rate_hz=rate,
        signal=kind if undo or kind == "raw" else sig.kind,
        source=sig.source,
        filters_before=filters_before,
        reliable_below_hz=reliable,
        rms_above_40hz_rad_s={a: float(rms[i]) for i, a in enumerate(AXES)},
        rms_above_40hz_interval_rad_s={a: [float(rlo[i]), float(rhi[i])] for i, a in enumerate(AXES)},
        rms_band_hz=[HIGHPASS_HZ, band_hi],
        accel_rms_above_40hz_m_s2=arms,
        lines=lines,
        bands=band_rows,
        band_variable=bv_name,
        notes=notes,
        warnings=warns,
        f_hz=f,
        band_psd=np.array(band_psd),
        band_psd_accel=np.array(band_apsd) if band_apsd else None,
        mean_psd=mean_psd,
        n_windows=K,
        nperseg=nper,
        energy_bands=energy,
        dominant_vibration=dominant,
    )


def _label(s: dict) -> str:
    if s.get("kind") == "notch":
        return f"notch {s['cutoff_hz']:g} Hz (Q {s.get('q', float('nan')):.2f})"
    if s.get("dynamic"):
        lo, hi = s.get("cutoff_hz", 0.0), s.get("max_hz", float("nan"))
        rng = f", {lo:g}-{hi:g} Hz" if (lo and hi and hi == hi) else ", range not in the header"
        return f"{s['kind']} (dynamic{rng})"
    return f"{s['kind']} {s['cutoff_hz']:g} Hz"


def _link_lines(bands: list, f: np.ndarray, rate: float, *, has_bv: bool, rotor: bool, reliable_hz: float) -> list:
    """Link per-band peaks into lines and give each its law (see the module docstring).

    Per axis: (1) *fixed* — a frequency found (±2 resolutions) in at least half the bands;
    (2) *moving* — among the remaining peaks, the straight line f = a + b·u (u the band
    variable) through two peaks of different bands that collects the most bands within
    ±max(3 resolutions, 6 %) (ties: the larger total line power), kept when it spans ≥ 3 bands
    and moves by more than 3 resolutions over their span; refitted by least squares, its peaks
    removed, repeated. A falling line is folded from above the logged Nyquist.
    """
    df = f[1] - f[0]
    res = ENBW_HANN * df
    out = []
    nb = len(bands)
    for ax in range(3):
        pk = [(bi, p) for bi, b in enumerate(bands) for p in b["_peaks"] if p.axis == ax]
        free = set(range(len(pk)))
        groups = []
        # (1) fixed lines
        order = sorted(free, key=lambda i: -pk[i][1].power)
        for i in order:
            if i not in free:
                continue
            bi, p = pk[i]
            members = {bi: i}
            for j in free:
                bj, q = pk[j]
                if bj != bi and abs(q.f_hz - p.f_hz) <= 2 * res:
                    if bj not in members or abs(q.f_hz - p.f_hz) < abs(pk[members[bj]][1].f_hz - p.f_hz):
                        members[bj] = j
            if nb == 1 or (has_bv and len(members) >= max(2, math.ceil(nb / 2))):
                groups.append(("fixed" if has_bv else None, sorted(members.values(), key=lambda k: pk[k][0])))
                free -= set(members.values())
        # (2) moving lines
        while has_bv and nb >= 3 and len(free) >= 3:
            fl = sorted(free)
            best = None
            for ii in range(len(fl)):
                for jj in range(ii + 1, len(fl)):
                    (b1, p1), (b2, p2) = pk[fl[ii]], pk[fl[jj]]
                    u1, u2 = bands[b1]["median"], bands[b2]["median"]
                    if b1 == b2 or u1 == u2:
                        continue
                    slope = (p2.f_hz - p1.f_hz) / (u2 - u1)
                    members = {}
                    for k in fl:
                        bk, q = pk[k]
                        pred = p1.f_hz + slope * (bands[bk]["median"] - u1)
                        tol = max(3 * res, 0.06 * pred)
                        if abs(q.f_hz - pred) <= tol and (bk not in members or q.power > pk[members[bk]][1].power):
                            members[bk] = k
                    score = (len(members), sum(pk[k][1].power for k in members.values()))
                    if best is None or score > best[0]:
                        best = (score, members)
            if best is None or best[0][0] < max(3, math.ceil(0.4 * nb)):
                break
            members = best[1]
            us = np.array([bands[b]["median"] for b in members])
            fs_ = np.array([pk[k][1].f_hz for k in members.values()])
            coef, cov = (
                np.polyfit(us, fs_, 1, cov=True) if len(us) > 3 else (np.polyfit(us, fs_, 1), np.full((2, 2), np.inf))
            )
            moving = abs(coef[0]) * np.ptp(us) > 3 * res and abs(coef[0]) > 2 * math.sqrt(max(cov[0, 0], 0.0))
            if not moving and abs(coef[0]) * np.ptp(us) > 3 * res:
                free -= {members[max(members, key=lambda b: 0)]} if False else set()
                # a slope not significant against the scatter: not a line, drop the seed pair's weakest peak
                weakest = min(members.values(), key=lambda k: pk[k][1].power)
                free.discard(weakest)
                continue
            if not moving:
                # a flat line that was not in half the bands: a fixed line seen in fewer bands
                groups.append(("fixed", sorted(members.values(), key=lambda k: pk[k][0])))
            else:
                groups.append(("moving", sorted(members.values(), key=lambda k: pk[k][0])))
            free -= set(members.values())
        for law, idx in groups:
            bidx = np.array([pk[k][0] for k in idx])
            fs_ = np.array([pk[k][1].f_hz for k in idx])
            pw = np.array([pk[k][1].power for k in idx])
            se = np.array([pk[k][1].power_se for k in idx])
            thr = np.array([bands[b]["median"] for b in bidx])
            entry = {"axis": AXES[ax]}
            if law == "moving":
                A = np.column_stack([np.ones_like(thr), thr])
                coef, *_ = np.linalg.lstsq(A, fs_, rcond=None)
                resid = fs_ - A @ coef
                s2 = float(resid @ resid / max(len(fs_) - 2, 1))
                cov = s2 * np.linalg.inv(A.T @ A)
                slope, slope_se = float(coef[1]), float(math.sqrt(max(cov[1, 1], 0.0)))
                t_med = float(np.median([b["median"] for b in bands]))
                f_med = float(coef[0] + coef[1] * t_med)
                i_med = int(np.argmin(np.abs(thr - t_med)))
                aliased = slope < 0
                entry.update(
                    {
                        "frequency_hz": f_med,
                        "follows": "throttle",
                        "amplitude_rad_s": float(math.sqrt(2 * pw[i_med])),
                        "amplitude_interval_rad_s": _amp_interval(pw[i_med], se[i_med]),
                        "law": {
                            "kind": "f = hz_at_zero + hz_per_unit * band variable",
                            "hz_at_zero": float(coef[0]),
                            "hz_per_unit": slope,
                            "hz_per_unit_se": slope_se,
                        },
                        "per_band": [
                            {
                                "band": int(b),
                                "throttle_median": float(bands[b]["median"]),
                                "frequency_hz": float(ff),
                                "amplitude_rad_s": float(math.sqrt(2 * pp)),
                            }
                            for b, ff, pp in zip(bidx, fs_, pw)
                        ],
                        "aliased": bool(aliased),
                    }
                )
                if aliased:
                    entry["unfolded_frequency_hz"] = float(rate - f_med)
                    entry["note"] = "apparent frequency falls as throttle rises: folded from above the logged Nyquist"
                if rotor:
                    rh = np.array([bands[b].get("rotor_hz_median", np.nan) for b in bidx])
                    fu = fs_ if not aliased else rate - fs_
                    h = float(np.nanmedian(fu / rh))
                    if np.isfinite(h) and round(h) >= 1 and abs(h - round(h)) < 0.1:
                        entry["follows"] = "erpm"
                        entry["harmonic"] = int(round(h))
            else:
                entry.update(
                    {
                        "frequency_hz": float(np.average(fs_, weights=pw) if pw.sum() > 0 else fs_.mean()),
                        "follows": law,
                        "amplitude_rad_s": float(math.sqrt(2 * np.mean(pw))),
                        "amplitude_interval_rad_s": _amp_interval(
                            float(np.mean(pw)), float(np.sqrt(np.sum(se**2)) / len(se))
                        ),
                        "n_bands": int(len(idx)),
                    }
                )
                if law is None:
                    entry["law_note"] = "no throttle variation: law not identifiable"
            entry["frequency_interval_hz"] = [entry["frequency_hz"] - res / 2, entry["frequency_hz"] + res / 2]
            entry["level_reliable"] = bool(entry["frequency_hz"] < reliable_hz)
            out.append(entry)
    # harmonic numbers of the moving (unfolded) throttle lines relative to the lowest on each axis
    for ax in AXES:
        mv = [e for e in out if e["axis"] == ax and e["follows"] == "throttle" and not e.get("aliased")]
        if mv:
            f0 = min(e["frequency_hz"] for e in mv)
            for e in mv:
                h = e["frequency_hz"] / f0
                e["harmonic"] = int(round(h)) if abs(h - round(h)) < 0.08 else None
    out.sort(key=lambda e: (e["axis"], -e["amplitude_rad_s"]))
    return out


def _amp_interval(power: float, se: float) -> list:
    if not np.isfinite(se):
        return [float("nan"), float("nan")]
    lo = math.sqrt(2 * max(power - 1.96 * se, 0.0))
    hi = math.sqrt(2 * (power + 1.96 * se))
    return [lo, hi]


# ------------------------------------------------------------------ spec file
def write_spec(res: VibrationResult, path: str | os.PathLike, *, source: str = "", overwrite: bool = True) -> dict:
    """Write the versioned vibration spec the simulator reads (JSON, atomically).

    Keys: ``format_version``, ``kind`` = "gyroharness.vibration_spec", ``source``, ``rate_hz``,
    ``signal``, ``filters_before``, ``band_variable``, ``f_hz`` (M,), ``bands`` (each:
    throttle span, median, ``psd_rad2_s2_hz`` {x,y,z: (M,)} in the raw domain, NaN → null
    where unreliable, accel PSD (m/s²)²/Hz when logged, RMS above 40 Hz, ``energy_bands`` of
    the band), ``lines`` and ``energy_bands`` (as :func:`analyse`), ``rms_above_40hz_rad_s``.
    Format 1.1 adds the energy bands (1.0 specs still read: the major version is checked).
    """

    def arr(a):
        return [None if not np.isfinite(v) else float(v) for v in np.asarray(a, float)]

    bands = []
    for i, b in enumerate(res.bands):
        d = {k: v for k, v in b.items() if k != "peaks_hz"}
        d["psd_rad2_s2_hz"] = {a: arr(res.band_psd[i][:, j]) for j, a in enumerate(AXES)}
        if res.band_psd_accel is not None:
            d["accel_psd_m2_s4_hz"] = {a: arr(res.band_psd_accel[i][:, j]) for j, a in enumerate(AXES)}
        bands.append(d)
    spec = {
        "format_version": SPEC_FORMAT_VERSION,
        "kind": "gyroharness.vibration_spec",
        "source": source,
        "rate_hz": res.rate_hz,
        "signal": res.signal,
        "filters_before": res.filters_before,
        "reconstructed_reliable_below_hz": res.reliable_below_hz,
        "band_variable": res.band_variable,
        "rms_above_40hz_rad_s": res.rms_above_40hz_rad_s,
        "lines": res.lines,
        "energy_bands": res.energy_bands,
        "f_hz": arr(res.f_hz),
        "bands": bands,
    }
    atomic_write_text(path, json.dumps(spec, indent=1, allow_nan=False) + "\n", overwrite=overwrite)
    return spec


def read_spec(path: str | os.PathLike) -> dict:
    """Read a vibration spec; one-line error for another major version or a non-spec file."""
    try:
        with open(path) as fh:
            spec = json.load(fh)
    except (OSError, json.JSONDecodeError) as exc:
        raise GyroInputError(f"{path}: not a readable vibration spec ({type(exc).__name__})") from None
    if not isinstance(spec, dict) or spec.get("kind") != "gyroharness.vibration_spec":
        raise GyroInputError(f"{path}: not a gyroharness vibration spec")
    major = str(spec.get("format_version", "")).split(".")[0]
    if major != SPEC_FORMAT_VERSION.split(".")[0]:
        raise GyroInputError(
            f"{path}: vibration spec format_version {spec.get('format_version')!r}; this build reads {SPEC_FORMAT_VERSION}"
        )
    return spec


# ------------------------------------------------------------------ plot
def plot_vibration(res: VibrationResult, path: str | os.PathLike, *, title: str = "") -> None:
    """Per axis: PSD per throttle band ((°/s)²/Hz, one absolute scale) with the lines overlaid,
    and the band × frequency spectrogram."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    f = res.f_hz
    conv = (180.0 / math.pi) ** 2
    fig, axs = plt.subplots(2, 3, figsize=(15, 8), constrained_layout=True)
    B = res.band_psd.shape[0]
    # decimals of the band labels: enough to tell adjacent bands apart (a 17-s flight's six bands
    # span 0.29-0.38 of the motor command: two decimals printed 0.34 three times)
    meds = [b["median"] for b in res.bands] + [x for b in res.bands for x in b["throttle"]]
    steps = np.diff(np.unique(np.round(meds, 6))) if len(meds) > 1 else np.array([])
    nd = int(min(4, max(2, -np.floor(np.log10(steps.min())) if steps.size and steps.min() > 0 else 2)))
    cmap = plt.get_cmap("viridis")
    shown = res.band_psd if res.band_psd.size else res.mean_psd
    finite = shown[np.isfinite(shown) & (shown > 0)] * conv
    vmin, vmax = (np.percentile(finite, 5), np.percentile(finite, 99.9)) if finite.size else (1e-4, 1)
    for j, a in enumerate(AXES):
        ax = axs[0, j]
        for i in range(B):
            thr = res.bands[i]["throttle"]
            ax.semilogy(
                f,
                res.band_psd[i][:, j] * conv,
                color=cmap(i / max(B - 1, 1)),
                lw=0.8,
                label=f"{thr[0]:.{nd}f}-{thr[1]:.{nd}f}",
            )
        if B == 0:  # too few windows for a band: the mean over every window analysed
            ax.semilogy(f, res.mean_psd[:, j] * conv, color="k", lw=0.8, label=f"all {res.n_windows} windows")
        for ln in res.lines:
            if ln["axis"] == a:
                ax.axvline(ln["frequency_hz"], color="r" if ln["follows"] != "fixed" else "k", ls=":", lw=0.8)
        if res.reliable_below_hz < f[-1]:
            ax.axvspan(res.reliable_below_hz, f[-1], color="0.85", zorder=0, label="undo unreliable (folding)")
        for eb in res.energy_bands:  # the energy bands (gyrocore.flight.energy_bands): extent shaded, share labelled
            if eb["axis"] == a and (eb.get("share_of_power_above_40hz") or 0.0) >= 0.05:
                ax.axvspan(
                    *eb["extent_hz"],
                    color="tab:orange",
                    alpha=0.3,
                    zorder=0.5,
                    label=f"band {eb['centre_hz']:.0f} Hz: {100 * eb['share_of_power_above_40hz']:.0f} % of rms power",
                )
        ax.set_ylim(vmin / 10, vmax * 3)
        ax.set_title(f"gyro {a} ({res.signal})")
        ax.set_xlabel("frequency, Hz")
        ax.set_ylabel("PSD, (deg/s)^2/Hz")
        if j == 0 or any(eb["axis"] == a for eb in res.energy_bands):
            ax.legend(title=(res.band_variable or "band").split(" ")[0], fontsize=7)
        ax2 = axs[1, j]
        if B > 1:
            Z = np.log10(np.maximum(res.band_psd[:, :, j] * conv, 1e-12))
            ax2.pcolormesh(
                np.concatenate([f - (f[1] - f[0]) / 2, [f[-1] + (f[1] - f[0]) / 2]]),
                np.arange(B + 1),
                Z,
                shading="flat",
                vmin=np.log10(vmin),
                vmax=np.log10(vmax),
            )
            ax2.set_yticks(np.arange(B) + 0.5, [f"{b['median']:.{nd}f}" for b in res.bands])
            for ln in res.lines:
                if ln["axis"] == a:
                    if "per_band" in ln:
                        ax2.plot(
                            [p["frequency_hz"] for p in ln["per_band"]],
                            [p["band"] + 0.5 for p in ln["per_band"]],
                            "r.-",
                            lw=0.8,
                        )
                    else:
                        ax2.axvline(ln["frequency_hz"], color="w", ls=":", lw=0.8)
            ax2.set_ylabel("band (median " + (res.band_variable or "").split(" ")[0] + ")")
            ax2.set_xlabel("frequency, Hz")
        else:
            ax2.set_axis_off()
            ax2.text(
                0.5,
                0.5,
                f"{B} throttle band{'s' if B != 1 else ''}: no band x frequency map",
                ha="center",
                va="center",
                transform=ax2.transAxes,
                color="0.4",
            )
    fig.suptitle(title or "vibration")
    from gyrocore.data.recording import atomic_open

    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------ synthesis (simulator side)
def spec_band(spec: dict, band: int | str = "middle") -> dict:
    """One band of a vibration spec: an index, or "middle" (the band with the median command)."""
    bands = spec.get("bands") or []
    if not bands:
        raise GyroInputError("vibration spec has no bands")
    if band == "middle":
        return bands[len(bands) // 2]
    try:
        return bands[int(band)]
    except (ValueError, IndexError):
        raise GyroInputError(f"vibration band {band!r}: the spec has bands 0..{len(bands) - 1} (or 'middle')") from None


def shaped_params(
    spec: dict,
    *,
    band: int | str = "middle",
    fmin_hz: float = HIGHPASS_HZ,
    exclude_hz: Sequence[tuple[float, float]] = (),
    subtract_lines: Sequence[tuple[float, dict]] = (),
) -> dict:
    """The shaped part of the registry effect ``vibration`` from one band of a spec.

    Returns ``{"f_hz": (n,), "psd_rad2_s2_hz": (3, n)}`` (the effect's schema, SI): the spec
    band's raw-domain gyro PSD per axis on the spec's grid, set to 0 below ``fmin_hz`` (the
    flight's own motion is not vibration), at and above the spec's reliable limit, in notch
    holes (no value) and inside the ``exclude_hz`` intervals (a line the simulator's physics
    already carries). The grid is cut to [first bin ≥ fmin − one bin, reliable limit + one bin]
    so the zeros at its ends are kept (linear interpolation then falls to 0 within one bin).
    ``subtract_lines``: ``(f_hz, {axis: power (rad/s)²})`` of lines the simulator's physics
    carries: within ± 3 bins of f_hz (a Hann window's main lobe and first side lobes hold > 99.9 %
    of a tone's power) the PSD's excess over the local floor (median of the bins 10..30 away) is
    removed up to the line's power, so the broadband under the line and any power the line
    detector did not attribute to the line (e.g. the line smeared by the throttle moving within
    the band) stay.
    ``sim.noise.ShapedNoise`` generates it; ``simulate --vibration SPEC`` and a preset's
    ``[vibration] spec = ...`` put it into ``SyntheticGyro`` as this effect's parameters.
    """
    b = spec_band(spec, band)
    f_spec = np.asarray(spec["f_hz"], float)
    lim = min(float(spec.get("reconstructed_reliable_below_hz") or f_spec[-1]), f_spec[-1])
    P = np.zeros((3, f_spec.size))
    for j, a in enumerate(AXES):
        s = np.array([np.nan if v is None else v for v in b["psd_rad2_s2_hz"][a]], float)
        S = np.nan_to_num(s, nan=0.0)
        S[(f_spec < fmin_hz) | (f_spec >= lim) | np.isnan(s)] = 0.0
        for lo, hi in exclude_hz:
            S[(f_spec >= lo) & (f_spec <= hi)] = 0.0
        dfs = float(f_spec[1] - f_spec[0])
        for f0, pw in subtract_lines:
            p_line = float(pw.get(a, 0.0)) if isinstance(pw, dict) else float(pw[j])
            if not p_line > 0:
                continue
            k = int(round((float(f0) - f_spec[0]) / dfs))
            side = np.r_[max(k - 30, 0) : max(k - 10, 0), min(k + 11, f_spec.size) : min(k + 31, f_spec.size)]
            floor = float(np.median(S[side])) if side.size else 0.0
            lo_k, hi_k = max(k - 3, 0), min(k + 4, f_spec.size)
            excess = np.maximum(S[lo_k:hi_k] - floor, 0.0)
            tot = float(excess.sum()) * dfs
            if tot > 0:
                S[lo_k:hi_k] -= excess * min(1.0, p_line / tot)
        P[j] = np.maximum(S, 0.0)
    df = float(f_spec[1] - f_spec[0])
    keep = (f_spec >= fmin_hz - 1.01 * df) & (f_spec <= lim + 1.01 * df)
    return {"f_hz": f_spec[keep].copy(), "psd_rad2_s2_hz": P[:, keep].copy()}


def synthesize(
    spec: dict,
    *,
    n: int,
    rate_hz: float,
    seed: int,
    band: int | str = "middle",
    fmin_hz: float = HIGHPASS_HZ,
    exclude_hz: Sequence[tuple[float, float]] = (),
) -> np.ndarray:
    """A gyro vibration disturbance (n, 3), rad/s, whose PSD is the spec band's raw-domain PSD.

    Random-phase synthesis: for each rfft bin k of length n at ``rate_hz``,
    X_k = √(S(f_k)·fs·n/2)·(g₁ + i g₂)/√2 with g ~ N(0, 1), so that the one-sided periodogram
    2|X_k|²/(fs·n) has expectation S(f_k); x = irfft(X). S is the spec's PSD interpolated
    linearly in f; zero below ``fmin_hz`` (the flight's own motion is not vibration), above
    the spec's reliable limit and its Nyquist, and where the spec has no value (notch holes).
    Gaussian: the lines come out as narrow-band noise of the measured power, not as
    phase-coherent sinusoids. ``seed``: ``np.random.default_rng(seed)``. ``exclude_hz``: (lo, hi)
    intervals, Hz, where S is set to 0 (a line the simulator's physics already carries).
    """
    b = spec_band(spec, band)
    f_spec = np.asarray(spec["f_hz"], float)
    lim = min(float(spec.get("reconstructed_reliable_below_hz") or f_spec[-1]), f_spec[-1])
    rng = np.random.default_rng(seed)
    f = np.fft.rfftfreq(n, d=1.0 / rate_hz)
    out = np.empty((n, 3))
    for j, a in enumerate(AXES):
        s = np.array([np.nan if v is None else v for v in b["psd_rad2_s2_hz"][a]], float)
        S = np.interp(f, f_spec, np.nan_to_num(s, nan=0.0), left=0.0, right=0.0)
        S[(f < fmin_hz) | (f >= lim)] = 0.0
        S[np.interp(f, f_spec, np.isnan(s).astype(float)) > 0] = 0.0
        for lo, hi in exclude_hz:
            S[(f >= lo) & (f <= hi)] = 0.0
        amp = np.sqrt(S * rate_hz * n / 2.0)
        X = amp * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)) / math.sqrt(2.0)
        X[0] = 0.0
        if n % 2 == 0:
            X[-1] = 0.0
        out[:, j] = np.fft.irfft(X, n)
    return out


def add_vibration(
    rec: Recording, spec: dict, *, seed: int, band: int | str = "middle", exclude_hz: Sequence[tuple[float, float]] = ()
) -> Recording:
    """``rec`` with :func:`synthesize`'s disturbance added to its gyro (open loop: the truth and
    any controller that flew the recording did not see it); metadata says so. ``exclude_hz`` as
    :func:`synthesize`."""
    d = synthesize(spec, n=rec.n, rate_hz=rec.rate_hz, seed=seed, band=band, exclude_hz=exclude_hz)
    b = spec_band(spec, band)
    return rec.with_gyro(
        rec.gyro_rad_s + d,
        vibration_spec=str(spec.get("source", "")),
        vibration_band=json.dumps({"throttle": b.get("throttle"), "median": b.get("median")}),
        vibration_injection="shaped Gaussian disturbance added to the measured gyro (open loop), seed "
        f"{seed}; PSD of the spec band above {HIGHPASS_HZ:g} Hz"
        + (f", without {', '.join(f'{lo:g}-{hi:g} Hz' for lo, hi in exclude_hz)}" if exclude_hz else ""),
    )


def fidelity(sim: VibrationResult, spec: dict, *, band: int | str = "middle", fmin_hz: float = HIGHPASS_HZ) -> dict:
    """In-band fraction: bins (fmin .. min(Nyquists, reliable limit)) where the simulated gyro's
    PSD is statistically indistinguishable from the real flight's band PSD.

    Under equal spectra the ratio of two averaged periodograms is F(ν_sim, ν_real)-distributed
    (ν from each one's window count, :func:`_dof`); a bin is in band when the ratio lies in the
    central 95 % of that F distribution, so a perfect match gives 0.95 on average.
    Also returns the median ratio (sim/real) and the RMS above fmin of both.
    """
    b = spec_band(spec, band)
    f_r = np.asarray(spec["f_hz"], float)
    lim = min(float(spec.get("reconstructed_reliable_below_hz") or f_r[-1]), f_r[-1], sim.f_hz[-1])
    nu_r = _dof(int(b["n_windows"]))
    nu_s = _dof(int(sim.n_windows))
    lo_q, hi_q = stats.f.ppf([0.025, 0.975], nu_s, nu_r)
    out = {}
    fs = sim.f_hz
    sel = (fs >= fmin_hz) & (fs < lim)
    for j, a in enumerate(AXES):
        real = np.array([np.nan if v is None else v for v in b["psd_rad2_s2_hz"][a]], float)
        R = np.interp(fs[sel], f_r, real)
        S = sim.mean_psd[sel, j]
        ok = np.isfinite(R) & np.isfinite(S) & (R > 0)
        ratio = S[ok] / R[ok]
        dfr = fs[1] - fs[0]
        out[a] = {
            "in_band_fraction": float(np.mean((ratio >= lo_q) & (ratio <= hi_q))) if ok.any() else float("nan"),
            "median_ratio_sim_to_real": float(np.median(ratio)) if ok.any() else float("nan"),
            "rms_sim_rad_s": float(np.sqrt(np.nansum(S) * dfr)),
            "rms_real_rad_s": float(np.sqrt(np.nansum(R) * dfr)),
            "band_hz": [fmin_hz, float(lim)],
        }
    return out
