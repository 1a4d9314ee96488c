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
import warnings
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from gyrocore.errors import GyroInputError
from gyrocore.data.recording import Recording, atomic_open, atomic_write_text
from gyrocore.flight.energy_bands import attach as attach_energy_bands
from gyrocore.flight.filters import SosFilter, biquad_notch, loop_scale, make_filter
from gyrocore.flight.spectra import (
    AXES,
    ENBW_HANN,
    MIN_BAND_WINDOWS,
    Windows,
    band_counts,
    dof,
    find_peaks,
    hann_windows,
)

__all__ = [
    "VibrationResult",
    "analyse",
    "write_spec",
    "read_spec",
    "SPEC_FORMAT_VERSION",
    "undo_response",
    "plot_vibration",
]
#: 1.1: ``energy_bands`` (whole flight, and per throttle band inside ``bands``; gyrocore.flight.energy_bands)
SPEC_FORMAT_VERSION = "1.1"
HIGHPASS_HZ = 40.0
#: Bins where the undone filters' |H|² is below −20 dB (around a notch) are not reconstructed:
#: dividing by it would amplify the logged noise floor and quantisation 100-fold.
H2_FLOOR = 1e-2


# ------------------------------------------------------------------ signal choice
def _stage_filter(stage: dict, loop_scale: float):
    """SosFilter of a static firmware stage (gyrocore.flight.filters), at its nominal rate scaled to the measured clock."""
    kind, fc, rate = stage["kind"], float(stage["cutoff_hz"]), float(stage["rate_hz"])
    if kind == "notch":
        flt = biquad_notch(fc, rate, q=float(stage["q"]))
    elif kind in ("pt1", "pt2", "pt3", "biquad"):
        flt = make_filter(kind, fc, rate)
    else:
        return None
    return SosFilter(flt.sos, rate_hz=rate * loop_scale, name=flt.name, cutoff_hz=fc)


def undo_response(
    stages: Sequence[dict], f_hz: np.ndarray, *, loop_scale: float = 1.0, log_rate_hz: float | None = None
):
    """|H(f)|² of the undoable (static) stages, the stages that cannot be undone, and the reliable band.

    Parameters
    ----------
    stages : list of dict
        Firmware stages (``gyrocore.readers.blackbox_firmware.FilterStage.to_dict``).
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
    rate, nper = _window_samples(rec.t_s, window_s)
    bv, bv_name = _band_variable(rec)
    airborne = _airborne(rec, bv, airborne_min_cmd=airborne_min_cmd, t_from_s=t_from_s, t_to_s=t_to_s)
    W = _signal_windows(rec, sig.gyro, bv, airborne, nperseg=nper, rate_hz=rate)
    f = W.f_hz
    und = _undo_filters(rec, sig, f, rate_hz=rate, undo=undo, notes=notes, warns=warns)
    psd = _reconstruct(W.psd, und.H2, f, notes)
    accel_psd = None
    if rec.accel_m_s2 is not None:
        accel_psd = hann_windows(rec.t_s, rec.accel_m_s2, bv, None, airborne, nperseg=nper, rate_hz=rate).psd
    df = f[1] - f[0]
    hp = (f >= HIGHPASS_HZ) & (f < und.reliable_hz + 0.5 * df)
    band_hi = float(f[hp][-1]) if hp.any() else float("nan")
    rms, rlo, rhi = _rms_stats(psd, hp, df)
    arms = None
    if accel_psd is not None:
        am, _, _ = _rms_stats(accel_psd, f >= HIGHPASS_HZ, df)
        arms = {a: float(am[i]) for i, a in enumerate(AXES)}
    edges = _throttle_edges(W.band_var, bv, band_edges=band_edges, n_bands=n_bands, window_s=window_s, notes=notes)
    bands = _throttle_bands(W, psd, accel_psd, und.H2, edges, hp=hp, fmin_hz=fmin_hz, notes=notes)
    has_law = bv is not None and len(edges) > 2
    lines = _link_lines(bands.rows, f, rate, has_bv=has_law, rotor=W.rotor_hz is not None, reliable_hz=und.reliable_hz)
    for r in bands.rows:
        pk = r.pop("_peaks")
        r["peaks_hz"] = {a: sorted(round(p.f_hz, 1) for p in pk if p.axis == i) for i, a in enumerate(AXES)}
    mean_psd = np.nanmean(psd, axis=0)
    energy, dominant = attach_energy_bands(
        f,
        psd,
        mean_psd,
        bands.psd,
        bands.rows,
        lines,
        fmin_hz=fmin_hz,
        reliable_below_hz=und.reliable_hz,
        rate_hz=rate,
        has_bv=has_law,
        dof=dof,
        resolution_hz=ENBW_HANN * df,
        band_windows=bands.windows,
    )
    return VibrationResult(
        format_version=SPEC_FORMAT_VERSION,
        rate_hz=rate,
        signal=und.kind if undo or und.kind == "raw" else sig.kind,
        source=sig.source,
        filters_before=und.filters_before,
        reliable_below_hz=und.reliable_hz,
        rms_above_40hz_rad_s={a: float(rms[i]) for i, a in enumerate(AXES)},
        rms_above_40hz_interval_rad_s={a: [float(rlo[i]), float(rhi[i])] for i, a in enumerate(AXES)},
        rms_band_hz=[HIGHPASS_HZ, band_hi],
        accel_rms_above_40hz_m_s2=arms,
        lines=lines,
        bands=bands.rows,
        band_variable=bv_name,
        notes=notes,
        warnings=warns,
        f_hz=f,
        band_psd=np.array(bands.psd),
        band_psd_accel=np.array(bands.psd_accel) if bands.psd_accel else None,
        mean_psd=mean_psd,
        n_windows=psd.shape[0],
        nperseg=nper,
        energy_bands=energy,
        dominant_vibration=dominant,
    )


# ------------------------------------------------------------------ the steps of analyse
def _window_samples(t_s: np.ndarray, window_s: float) -> tuple[float, int]:
    """The data rate, Hz, and the (even) samples per Hann window of ``window_s`` seconds."""
    rate = 1.0 / float(np.median(np.diff(t_s)))
    nper = int(round(window_s * rate))
    if nper < 32:
        raise GyroInputError(f"window of {window_s} s holds {nper} samples at {rate:.0f} Hz; use a longer --window-s")
    return rate, nper + nper % 2


def _airborne(rec: Recording, bv, *, airborne_min_cmd: float, t_from_s, t_to_s) -> np.ndarray:
    """(N,) bool: the samples analysed (band variable at or above the airborne threshold, inside
    the time span); one ``error:`` line when the span or the airborne part is empty."""
    t = rec.t_s
    airborne = np.ones(rec.n, bool)
    if bv is not None:
        airborne &= np.isfinite(bv) & (bv >= airborne_min_cmd)
    spanned = t_from_s is not None or t_to_s is not None
    in_span = np.ones(rec.n, bool)
    if t_from_s is not None:
        in_span &= t >= t_from_s
    if t_to_s is not None:
        in_span &= t < t_to_s
    airborne &= in_span
    if spanned and not in_span.any():
        raise GyroInputError(f"--t-from-s/--t-to-s select 0 samples; the recording spans t = {t[0]:g}-{t[-1]:g} s")
    if not airborne.any():
        raise GyroInputError(
            "no airborne samples (band variable below the airborne threshold everywhere"
            + (" in the selected time span)" if spanned else ")")
        )
    return airborne


def _signal_windows(rec: Recording, x, bv, airborne, *, nperseg: int, rate_hz: float) -> Windows:
    """:func:`~gyrocore.flight.spectra.hann_windows` of the analysed gyro; a batch-sampled recording's error names the longest window it holds."""
    try:
        return hann_windows(rec.t_s, x, bv, _rotor_hz(rec), airborne, nperseg=nperseg, rate_hz=rate_hz)
    except GyroInputError as exc:
        if rec.meta.get("stream") == "batch" and rec.meta.get("batch_window_s"):
            wb = float(rec.meta["batch_window_s"])
            raise GyroInputError(
                f"{exc}: the batch sampler's windows are {wb:.3g} s long; use --window-s "
                f"{math.floor(wb * 0.95 * 100) / 100:g} or less"
            ) from None
        raise


@dataclass(frozen=True)
class _Undone:
    H2: np.ndarray  # (M,) |H(f)|² of the undone stages (1 where none)
    filters_before: list  # the stages before the analysed signal, each with "undone"
    kind: str  # raw / partly_filtered / filtered
    reliable_hz: float  # reconstruction reliable below this


def _undo_filters(rec: Recording, sig: _Signal, f: np.ndarray, *, rate_hz: float, undo: bool, notes, warns) -> _Undone:
    """The firmware filters the analysed signal went through, undone in the spectral domain where
    they are static (``undo``); what was and was not undone goes to ``notes`` / ``warns``."""
    kind = sig.kind
    filters_before = [dict(s, undone=False) for s in sig.stages_before]
    H2 = np.ones_like(f)
    reliable = float(f[-1])
    if sig.stages_before and undo:
        H2, done, not_done, reliable = undo_response(
            sig.stages_before, f, loop_scale=loop_scale(rec.meta), log_rate_hz=rate_hz
        )
        filters_before = done + not_done
        kind = "raw" if not not_done else "partly_filtered"
        if done:
            notes.append(
                "undone in the spectrum (|H|^2 divided out): "
                + ", ".join(_label(s) for s in done)
                + f"; reliable below {reliable:.0f} Hz (folding from above the logged Nyquist {rate_hz / 2:.0f} Hz)"
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
    return _Undone(H2, filters_before, kind, reliable)


def _reconstruct(psd_w: np.ndarray, H2: np.ndarray, f: np.ndarray, notes: list) -> np.ndarray:
    """(K, M, 3) per-window PSD divided by |H|²; NaN where |H|² < H2_FLOOR (said in ``notes``).
    Above the reliable limit it is kept for the plot and the spec, flagged, not integrated."""
    psd = psd_w / H2[None, :, None]
    hole = H2 < H2_FLOOR
    psd[:, hole, :] = np.nan
    if hole.any():
        edges_h = np.flatnonzero(np.diff(np.concatenate([[0], hole.astype(int), [0]])))
        spans = [(float(f[a]), float(f[b - 1])) for a, b in zip(edges_h[::2], edges_h[1::2])]
        notes.append(
            "not reconstructed (undone filters below -20 dB): " + ", ".join(f"{a:.0f}-{b:.0f} Hz" for a, b in spans)
        )
    return psd


def _rms_stats(P: np.ndarray, mask: np.ndarray, df: float):
    """RMS over the ``mask`` bins of the window-averaged PSD ``P`` (K, M, 3) and its 95 % interval
    from the spread of the per-window band power (K_eff = ν/2 windows): three (3,) arrays."""
    pw = np.nansum(P[:, mask, :], axis=1) * df  # (K, 3) per-window band power
    m = pw.mean(axis=0)
    k_eff = max(dof(P.shape[0]) / 2.0, 1.0)
    se = pw.std(axis=0, ddof=1) / math.sqrt(k_eff) if P.shape[0] > 1 else np.full(3, np.nan)
    lo = np.sqrt(np.clip(m - 1.96 * se, 0, None))
    hi = np.sqrt(m + 1.96 * se)
    return np.sqrt(m), lo, hi


def _throttle_edges(band_var: np.ndarray, bv, *, band_edges, n_bands: int, window_s: float, notes: list) -> np.ndarray:
    """The throttle band edges: the given ones, else equal-count quantiles of the windows' band
    variable (as many bands as asked while each keeps MIN_BAND_WINDOWS), else one band."""
    K = band_var.size
    if band_edges is not None:
        edges = np.asarray(band_edges, float)
        if edges.ndim != 1 or edges.size < 2 or not np.all(np.diff(edges) > 0):
            raise GyroInputError(f"band edges must be an increasing list of at least 2 values, got {list(band_edges)}")
        if bv is None:
            raise GyroInputError("band edges need a motor or throttle column")
        return edges
    if bv is not None and np.ptp(band_var) > 0.02:
        # a band with fewer windows is not analysed: on a 17-s flight 8 bands of 3 windows
        # had dropped 18 of 26 windows, and the flight's motor line with them
        for nb in range(max(1, min(int(n_bands), K // MIN_BAND_WINDOWS)), 0, -1):
            edges = np.unique(np.quantile(band_var, np.linspace(0, 1, nb + 1)))
            if min(band_counts(band_var, edges)) >= MIN_BAND_WINDOWS:
                break
        if len(edges) - 1 < n_bands:
            notes.append(
                f"{len(edges) - 1} throttle band(s) instead of {n_bands}: {K} windows of {window_s:g} s, "
                f"each band needs at least {MIN_BAND_WINDOWS}"
            )
        return edges
    if bv is not None:
        notes.append("no throttle variation: lines have no throttle law")
        return np.array([band_var.min(), band_var.max()])
    notes.append("no motor or throttle column: one band, lines have no throttle law")
    return np.array([0.0, 0.0])


@dataclass(frozen=True)
class _Bands:
    rows: list  # one dict per analysed band (its peaks under "_peaks" until the lines are linked)
    psd: list  # (M, 3) raw-domain PSD per band
    psd_accel: list  # (M, 3) accel PSD per band (empty without accel)
    windows: list  # (K,) bool: the windows of each band


def _throttle_bands(W: Windows, psd, accel_psd, H2, edges, *, hp, fmin_hz: float, notes: list) -> _Bands:
    """Per throttle band with at least MIN_BAND_WINDOWS windows: its PSD, RMS, accel RMS and
    peaks (line power in the raw domain); the bands left out are said in ``notes``."""
    f = W.f_hz
    df = f[1] - f[0]
    K = psd.shape[0]
    out = _Bands([], [], [], [])
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
        b_rms, b_lo, b_hi = _rms_stats(psd[sel], hp, df)
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
            out.psd_accel.append(np.nanmean(accel_psd[sel], axis=0))
            am_, _, _ = _rms_stats(accel_psd[sel], f >= HIGHPASS_HZ, df)
            row["accel_rms_above_40hz_m_s2"] = {a: float(am_[i]) for i, a in enumerate(AXES)}
        row["_peaks"] = _raw_domain_peaks(W, sel, H2, fmin_hz=fmin_hz)
        out.rows.append(row)
        out.psd.append(np.nanmean(psd[sel], axis=0))
        out.windows.append(sel)
    if dropped:
        notes.append(
            "not analysed (fewer than %d windows): " % MIN_BAND_WINDOWS
            + ", ".join(f"band {a:.3g}-{b:.3g} ({n} windows)" for a, b, n in dropped)
            + ("" if out.rows else "; no band spectra or lines, the rms is over all windows")
        )
    return out


def _raw_domain_peaks(W: Windows, sel: np.ndarray, H2: np.ndarray, *, fmin_hz: float) -> list:
    """The peaks of the ``sel`` windows' logged PSD, their power scaled by 1/|H|² at the line
    (smooth across ±2 bins); a peak inside a notch hole is dropped."""
    f = W.f_hz
    df = f[1] - f[0]
    peaks = find_peaks(
        f,
        np.nanmean(W.psd[sel], axis=0),
        W.psd[sel],
        int(sel.sum()),
        fmin=fmin_hz,
        fmax=f[-1] - 2 * df,
        df_res=ENBW_HANN * df,
    )
    kept = []
    for p in peaks:
        g = float(np.interp(p.f_hz, f, H2))
        if g < H2_FLOOR:
            continue
        p.power /= g
        p.power_se /= g
        kept.append(p)
    return kept


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
    res = ENBW_HANN * (f[1] - f[0])
    out = []
    for ax in range(3):
        pk = [(bi, p) for bi, b in enumerate(bands) for p in b["_peaks"] if p.axis == ax]
        free = set(range(len(pk)))
        groups = _fixed_lines(pk, free, n_bands=len(bands), has_bv=has_bv, res_hz=res)
        if has_bv:
            groups += _moving_lines(pk, free, bands, res_hz=res)
        for law, idx in groups:
            if law == "moving":
                entry = _moving_line(pk, idx, bands, axis=ax, rate=rate, rotor=rotor)
            else:
                entry = _fixed_line(pk, idx, law, axis=ax)
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


def _fixed_lines(pk: list, free: set, *, n_bands: int, has_bv: bool, res_hz: float) -> list:
    """Groups ``(law, peak indices)`` of the peaks ``pk`` ((band, Peak) of one axis) at one
    frequency (±2 resolutions) in at least half the bands, strongest first; their peaks leave ``free``."""
    groups = []
    for i in sorted(free, key=lambda i: -pk[i][1].power):
        if i not in free:
            continue
        bi, p = pk[i]
        members = {bi: i}
        for j in free:
            bj, q = pk[j]
            if bj != bi and abs(q.f_hz - p.f_hz) <= 2 * res_hz:
                if bj not in members or abs(q.f_hz - p.f_hz) < abs(pk[members[bj]][1].f_hz - p.f_hz):
                    members[bj] = j
        if n_bands == 1 or (has_bv and len(members) >= max(2, math.ceil(n_bands / 2))):
            groups.append(("fixed" if has_bv else None, sorted(members.values(), key=lambda k: pk[k][0])))
            free -= set(members.values())
    return groups


def _best_straight_line(pk: list, fl: list, bands: list, res_hz: float):
    """The straight line f = a + b·u through two peaks of ``fl`` that collects the most bands
    within ±max(3 resolutions, 6 %) (ties: the larger total power): ``((n, power), {band: peak})``."""
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
                tol = max(3 * res_hz, 0.06 * pred)
                if abs(q.f_hz - pred) <= tol and (bk not in members or q.power > pk[members[bk]][1].power):
                    members[bk] = k
            score = (len(members), sum(pk[k][1].power for k in members.values()))
            if best is None or score > best[0]:
                best = (score, members)
    return best


def _moving_lines(pk: list, free: set, bands: list, *, res_hz: float) -> list:
    """Groups ``(law, peak indices)`` of the lines that move with the band variable, taken one
    at a time from the ``free`` peaks (a straight line too flat to move over its span is a fixed
    line seen in fewer than half the bands)."""
    groups = []
    nb = len(bands)
    while nb >= 3 and len(free) >= 3:
        best = _best_straight_line(pk, sorted(free), bands, res_hz)
        if best is None or best[0][0] < max(3, math.ceil(0.4 * nb)):
            break
        members = best[1]
        us = np.array([bands[b]["median"] for b in members])
        fs_ = np.array([pk[k][1].f_hz for k in members.values()])
        coef, cov = (
            np.polyfit(us, fs_, 1, cov=True) if len(us) > 3 else (np.polyfit(us, fs_, 1), np.full((2, 2), np.inf))
        )
        moving = abs(coef[0]) * np.ptp(us) > 3 * res_hz and abs(coef[0]) > 2 * math.sqrt(max(cov[0, 0], 0.0))
        if not moving and abs(coef[0]) * np.ptp(us) > 3 * res_hz:
            # a slope not significant against the scatter: not a line, drop the seed pair's weakest peak
            free.discard(min(members.values(), key=lambda k: pk[k][1].power))
            continue
        groups.append(("moving" if moving else "fixed", sorted(members.values(), key=lambda k: pk[k][0])))
        free -= set(members.values())
    return groups


def _moving_line(pk: list, idx: list, bands: list, *, axis: int, rate: float, rotor: bool) -> dict:
    """The JSON entry of a line that follows the band variable: its least-squares law, its level
    at the median band, per band, folded (falling) or not, an eRPM harmonic when a rotor column exists."""
    bidx = np.array([pk[k][0] for k in idx])
    fs_ = np.array([pk[k][1].f_hz for k in idx])
    pw = np.array([pk[k][1].power for k in idx])
    se = np.array([pk[k][1].power_se for k in idx])
    thr = np.array([bands[b]["median"] for b in bidx])
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
    entry = {
        "axis": AXES[axis],
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
    return entry


def _fixed_line(pk: list, idx: list, law: str | None, *, axis: int) -> dict:
    """The JSON entry of a line at one frequency: power-weighted frequency, mean level over its
    bands (``law`` None: no throttle variation to tell fixed from moving)."""
    fs_ = np.array([pk[k][1].f_hz for k in idx])
    pw = np.array([pk[k][1].power for k in idx])
    se = np.array([pk[k][1].power_se for k in idx])
    entry = {
        "axis": AXES[axis],
        "frequency_hz": float(np.average(fs_, weights=pw) if pw.sum() > 0 else fs_.mean()),
        "follows": law,
        "amplitude_rad_s": float(math.sqrt(2 * np.mean(pw))),
        "amplitude_interval_rad_s": _amp_interval(float(np.mean(pw)), float(np.sqrt(np.sum(se**2)) / len(se))),
        "n_bands": int(len(idx)),
    }
    if law is None:
        entry["law_note"] = "no throttle variation: law not identifiable"
    return entry


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
    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=110)
    plt.close(fig)
