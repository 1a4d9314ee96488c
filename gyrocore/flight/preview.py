"""Preview gyro filter chains on a flight's own spectrum, and choose one.

"What would this setting have done to this flight, without flying": every candidate chain is
built as the firmware runs it (:func:`gyrocore.flight.filters.firmware_stage`: Betaflight's PT1/PT2/
PT3/biquad/notch coefficients at its loop rate; PX4's and ArduPilot's 2nd-order Butterworth;
the article's first-order filter) and applied to the flight's gyro spectrum *before* the
firmware's filters (:mod:`gyrocore.flight.vibration`: logged unfiltered, or the static filters
undone). The filters are linear and time-invariant, so the spectrum after a chain is
S_raw(f)·|H(f)|²: the same as filtering the unfiltered gyro at the loop rate and logging it,
but computable from a decimated log (the time-domain filter would need the un-decimated
signal). Everything is on one absolute scale, (rad/s)²/Hz (plots: (°/s)²/Hz), so several
logs and candidates compare directly.

Scores of a chain (first version: an open-loop spectral / delay cost model on the recorded
gyro; the closed-loop simulator version is ``gyroharness filter-closed-loop``,
``experiments/flight_filter.py``):

* ``delay_ms`` — mean group delay of the chain over the flight band (default 1–30 Hz);
* ``phase_deg_at_hz`` — phase lag at the band's upper edge;
* ``gyro_noise_rad_s`` — RMS of the filtered gyro above 40 Hz (below the reliable limit);
* ``motor_noise`` — RMS of the *derivative* of the filtered gyro above 40 Hz, rad/s²: what
  the PID's D term turns into motor-command noise (motor noise = K_d × this);
* ``attitude_cost`` — attitude error, deg: the delay seen by the rate loop turns the flight's
  own angular rate into an attitude lag θ_d = τ·ω_rms (ω_rms: RMS of the gyro below 30 Hz
  over the airborne part), combined (root sum of squares) with the attitude jitter the
  passed vibration causes if tracked, θ_v = √∫ S_raw|H|²/(2πf)² df.

Recommendation: the least ``attitude_cost`` among the chains whose ``motor_noise`` does not
exceed the budget: the as-flown chain's motor noise (the pilot flew it and the motors coped),
else the firmware default's. The Pareto front (cost vs motor noise) is returned too.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import signal

from gyrocore.flight.filters import betaflight_notch_q, chain_filters, chain_response, loop_scale
from gyrocore.flight.vibration import analyse

__all__ = [
    "Candidate",
    "preview",
    "candidates",
    "recommend_filter",
    "notch_targets",
    "band_coverage",
    "recommend",
    "betaflight_cli",
    "CUTOFF_GRID_HZ",
]

CUTOFF_GRID_HZ = (40.0, 50.0, 60.0, 70.0, 80.0, 90.0, 100.0, 120.0, 140.0, 160.0, 180.0, 200.0, 250.0, 300.0)
LP_KINDS = ("pt1", "pt2", "pt3", "biquad")
FLIGHT_BAND_HZ = (1.0, 30.0)


@dataclass(frozen=True)
class Candidate:
    """A gyro filter chain: ``stages`` (firmware stage dicts) and what it is called."""

    name: str
    stages: tuple
    family: str = "betaflight"
    lowpass: str = "none"
    cutoff_hz: float = float("nan")
    notches_hz: tuple = ()


def _stage(kind, fc, rate, **kw):
    d = {"kind": kind, "cutoff_hz": float(fc), "rate_hz": float(rate), "dynamic": False, "header": "candidate"}
    d.update(kw)
    return d


def notch_stage(f0: float, width_hz: float, rate: float) -> dict:
    """Betaflight static notch covering ``width_hz`` (lower −3 dB edge f0 − width/2)."""
    cut = max(f0 - width_hz / 2.0, 0.3 * f0)
    return _stage("notch", f0, rate, notch_cutoff_hz=float(round(cut)), q=betaflight_notch_q(f0, round(cut)))


#: Smallest share of the rms power above 40 Hz for an energy band to get a static notch candidate.
BAND_NOTCH_MIN_SHARE = 0.1


def notch_targets(
    lines: Sequence[dict] = (), bands: Sequence[dict] = (), *, nyquist_hz: float | None = None
) -> list[tuple]:
    """Static-notch targets ``(f0_hz, width_hz, what)``, at most two (Betaflight has two static notches).

    Energy bands first (:mod:`gyrocore.flight.energy_bands`, whole flight, by share; those carrying at
    least :data:`BAND_NOTCH_MIN_SHARE` of the rms power above 40 Hz and not folded): the notch is centred on the
    band's centre with its −3 dB width the band's width (``notch_stage``: lower edge at
    centre − width/2), so it sits where the energy is; then the identified lines outside those
    bands (width = the line's frequency span over the throttle bands, at least 40 Hz), by
    amplitude; targets closer than 20 Hz to one already taken are skipped.
    """
    uniq: list[tuple] = []
    for b in bands:
        share = b.get("share_of_power_above_40hz")
        if share is None or not share >= BAND_NOTCH_MIN_SHARE or b.get("aliased"):
            continue  # a folded band's true frequency is above the logged Nyquist (as for lines)
        f0 = float(b["centre_hz"])
        if nyquist_hz and f0 >= nyquist_hz:
            continue
        if all(abs(f0 - u[0]) > 20 for u in uniq):
            uniq.append(
                (f0, float(b["width_hz"]), f"band {b['axis']} {b['edges_hz'][0]:.0f}-{b['edges_hz'][1]:.0f} Hz")
            )
    inside = [
        (b["extent_hz"][0], b["extent_hz"][1])
        for b in bands
        if (b.get("share_of_power_above_40hz") or 0.0) >= BAND_NOTCH_MIN_SHARE and not b.get("aliased")
    ]
    for ln in sorted(lines, key=lambda x: -x["amplitude_rad_s"]):
        f0 = ln.get("unfolded_frequency_hz") if ln.get("aliased") else ln["frequency_hz"]
        if nyquist_hz and f0 >= nyquist_hz:
            continue
        if any(lo <= f0 <= hi for lo, hi in inside):
            continue
        span = [p["frequency_hz"] for p in ln.get("per_band", [])]
        width = max(40.0, (max(span) - min(span)) if span else 0.0)
        if all(abs(f0 - u[0]) > 20 for u in uniq):
            uniq.append((float(f0), float(width), f"line {ln['axis']} {f0:.0f} Hz"))
    return uniq[:2]


def candidates(
    rate_hz: float,
    *,
    lines: Sequence[dict] = (),
    as_flown: Sequence[dict] | None = None,
    nyquist_hz: float | None = None,
    bands: Sequence[dict] = (),
) -> list[Candidate]:
    """Candidate chains at the firmware filter rate ``rate_hz``.

    Betaflight low-pass kinds × :data:`CUTOFF_GRID_HZ`; each with static notches at the
    :func:`notch_targets` (the energy bands ``bands`` first, then the identified lines) that the
    low-pass leaves above −20 dB (at most two, Betaflight has two static notches); the as-flown
    chain (static part); firmware defaults: Betaflight 4.x
    static part (LPF1 PT1 at its dynamic minimum 250 Hz + LPF2 PT1 500 Hz; its dynamic notch
    and RPM filter are dynamic and left out, said in the output), PX4 ``IMU_GYRO_CUTOFF`` 40 Hz
    (2nd-order Butterworth), ArduPilot ``INS_GYRO_FILTER`` 20 Hz (2nd-order Butterworth
    biquad); the article's first-order 30 Hz filter.
    """
    out: list[Candidate] = [Candidate("none", (), lowpass="none")]
    for k in LP_KINDS:
        for fc in CUTOFF_GRID_HZ:
            if fc * 2.0 >= rate_hz / 2:
                continue
            out.append(Candidate(f"{k} {fc:g} Hz", (_stage(k, fc, rate_hz),), lowpass=k, cutoff_hz=fc))
    # static notches at the energy bands and the identified lines
    uniq = [(f0, w) for f0, w, _ in notch_targets(lines, bands, nyquist_hz=nyquist_hz)]
    if uniq:
        base = [c for c in out if c.lowpass != "none"]
        for c in base:
            from gyrocore.flight.filters import firmware_stage

            lp = firmware_stage(c.stages[0])
            keep = [(f0, w) for f0, w in uniq if lp.magnitude(f0) > 0.1]
            if not keep:
                continue
            st = c.stages + tuple(notch_stage(f0, w, rate_hz) for f0, w in keep)
            out.append(
                Candidate(
                    c.name + " + notch " + ",".join(f"{f0:.0f}" for f0, _ in keep),
                    st,
                    lowpass=c.lowpass,
                    cutoff_hz=c.cutoff_hz,
                    notches_hz=tuple(f0 for f0, _ in keep),
                )
            )
    if as_flown is not None:
        # each low-pass of the grid with the pilot's own static notches (re-rated to this loop)
        flown_notches = tuple(
            dict(s, rate_hz=float(rate_hz), header="as flown")
            for s in as_flown
            if s["kind"] == "notch" and not s.get("dynamic")
        )
        if flown_notches:
            for c in [c for c in out if c.lowpass in LP_KINDS and not c.notches_hz]:
                out.append(
                    Candidate(
                        c.name + " + flown notch " + ",".join(f"{s['cutoff_hz']:.0f}" for s in flown_notches),
                        c.stages + flown_notches,
                        lowpass=c.lowpass,
                        cutoff_hz=c.cutoff_hz,
                        notches_hz=tuple(s["cutoff_hz"] for s in flown_notches),
                    )
                )
        st = tuple(s for s in as_flown if not s.get("dynamic") and s["kind"] != "fir")
        lp = [s for s in st if s["kind"] in LP_KINDS]
        out.append(
            Candidate(
                "as flown",
                st,
                family="as_flown",
                lowpass=lp[0]["kind"] if lp else "none",
                cutoff_hz=lp[0]["cutoff_hz"] if lp else float("nan"),
                notches_hz=tuple(s["cutoff_hz"] for s in st if s["kind"] == "notch"),
            )
        )
    if 500.0 * 2 < rate_hz:
        out.append(
            Candidate(
                "betaflight 4.x default (static part)",
                (_stage("pt1", 250, rate_hz), _stage("pt1", 500, rate_hz)),
                family="betaflight_default",
                lowpass="pt1",
                cutoff_hz=250.0,
            )
        )
    out.append(
        Candidate(
            "px4 default IMU_GYRO_CUTOFF 40",
            (_stage("butter2", 40, rate_hz),),
            family="px4_default",
            lowpass="butter2",
            cutoff_hz=40.0,
        )
    )
    out.append(
        Candidate(
            "ardupilot default INS_GYRO_FILTER 20",
            (_stage("butter2", 20, rate_hz),),
            family="ardupilot_default",
            lowpass="butter2",
            cutoff_hz=20.0,
        )
    )
    out.append(
        Candidate(
            "article 1st-order 30 Hz",
            (_stage("article", 30, rate_hz),),
            family="article",
            lowpass="article",
            cutoff_hz=30.0,
        )
    )
    return out


def preview(
    f_hz: np.ndarray,
    psd_raw: np.ndarray,
    cand: Candidate,
    *,
    reliable_below_hz: float,
    omega_rms_rad_s: float,
    loop_scale: float = 1.0,
    flight_band_hz=FLIGHT_BAND_HZ,
    lines: Sequence[dict] = (),
    bands: Sequence[dict] = (),
) -> dict:
    """Spectrum after ``cand`` and its scores (see the module docstring).

    Parameters
    ----------
    f_hz : ndarray (M,)
    psd_raw : ndarray (M, 3)
        Gyro PSD before every firmware filter, (rad/s)²/Hz (one-sided).
    omega_rms_rad_s : float
        RMS angular rate of the flight below 30 Hz (all axes), rad/s.
    bands : list of dict
        Energy bands (:mod:`gyrocore.flight.energy_bands`): ``bands_left`` gives, per band, the
        fraction of its power (over its extent, on its axis) the chain lets through.
    """
    r = chain_response(cand.stages, f_hz, loop_scale=loop_scale)
    H2 = r.magnitude**2
    after = psd_raw * H2[:, None]
    df = f_hz[1] - f_hz[0]
    band = (f_hz >= 40.0) & (f_hz < reliable_below_hz)
    gyro_noise = np.sqrt(np.nansum(after[band], axis=0) * df)  # NaN: bins not reconstructed (notch holes)
    w = 2 * np.pi * f_hz
    motor = np.sqrt(np.nansum(after[band] * (w[band, None] ** 2), axis=0) * df)
    jitter = np.sqrt(np.nansum(after[band] / (w[band, None] ** 2), axis=0) * df)
    fb = np.linspace(flight_band_hz[0], flight_band_hz[1], 30)
    rb = chain_response(cand.stages, np.concatenate([fb, [flight_band_hz[1]]]), loop_scale=loop_scale)
    tau = float(np.mean(rb.group_delay_s[:-1]))
    # phase at the band edge from the exact frequency response of the cascade
    ph = 0.0
    for flt in chain_filters(cand.stages, loop_scale=loop_scale):
        _, h = signal.sosfreqz(flt.sos, worN=[flight_band_hz[1]], fs=flt.rate_hz)
        ph += float(np.angle(h[0], deg=True))
    theta_d = tau * omega_rms_rad_s
    theta_v = float(np.sqrt(np.sum(jitter**2)))
    line_left = []
    for ln in lines:
        f0 = ln["frequency_hz"]
        g = float(np.interp(f0, f_hz, r.magnitude))
        line_left.append(
            {
                "axis": ln["axis"],
                "frequency_hz": f0,
                "fraction_left": g,
                "amplitude_after_rad_s": ln["amplitude_rad_s"] * g,
            }
        )
    bands_left = []
    for b in bands:
        j = "xyz".index(b["axis"])
        inb = (f_hz >= b["extent_hz"][0]) & (f_hz <= b["extent_hz"][1])
        p0 = float(np.nansum(psd_raw[inb, j]))
        bands_left.append(
            {
                "axis": b["axis"],
                "centre_hz": b["centre_hz"],
                "extent_hz": b["extent_hz"],
                "power_fraction_left": float(np.nansum(after[inb, j]) / p0) if p0 > 0 else float("nan"),
            }
        )
    return {
        "name": cand.name,
        "family": cand.family,
        "filter": cand.lowpass,
        "cutoff_hz": cand.cutoff_hz,
        "notches_hz": list(cand.notches_hz),
        "stages": list(cand.stages),
        "delay_ms": 1e3 * tau,
        "phase_deg_at_hz": [ph, flight_band_hz[1]],
        "gyro_noise_rad_s": {a: float(gyro_noise[i]) for i, a in enumerate("xyz")},
        "motor_noise": float(np.sqrt(np.sum(motor**2))),
        "attitude_cost": float(np.degrees(math.hypot(theta_d, theta_v))),
        "attitude_cost_delay_deg": float(np.degrees(theta_d)),
        "attitude_cost_vibration_deg": float(np.degrees(theta_v)),
        "lines_left": line_left,
        "bands_left": bands_left,
        "psd_after": after,
    }


def recommend(rows: Sequence[dict]) -> tuple[dict, float, str, list]:
    """Least attitude cost under the motor-noise budget; returns (row, budget, budget source, Pareto front)."""
    by = {r["family"]: r for r in rows}
    if "as_flown" in by:
        budget, src = by["as_flown"]["motor_noise"], "as flown"
    elif "betaflight_default" in by:
        budget, src = by["betaflight_default"]["motor_noise"], "betaflight 4.x default (static part)"
    else:
        budget, src = min(r["motor_noise"] for r in rows), "least noise"
    pool = [r for r in rows if r["family"] in ("betaflight", "as_flown") and r["motor_noise"] <= budget * (1 + 1e-9)]
    if not pool:
        pool = [min((r for r in rows if r["family"] == "betaflight"), key=lambda r: r["motor_noise"])]
    best = min(pool, key=lambda r: (r["attitude_cost"], r["motor_noise"]))
    front = []
    for r in sorted((r for r in rows if r["family"] == "betaflight"), key=lambda r: r["motor_noise"]):
        if not front or r["attitude_cost"] < front[-1]["attitude_cost"]:
            front.append(r)
    return (
        best,
        budget,
        src,
        [
            {
                "name": r["name"],
                "motor_noise": r["motor_noise"],
                "attitude_cost": r["attitude_cost"],
                "delay_ms": r["delay_ms"],
            }
            for r in front
        ],
    )


_BF_TYPE = {"pt1": "PT1", "biquad": "BIQUAD", "pt2": "PT2", "pt3": "PT3"}


def betaflight_cli(row: dict, version: tuple | None) -> list[str]:
    """``set`` lines for Betaflight ``version`` (CLI names read in each tag's cli.c / settings.c).

    3.1.x: gyro_lowpass_type, gyro_lowpass, gyro_notchN_hz, gyro_notchN_cut; 3.2–4.2:
    gyro_lowpass_type, gyro_lowpass_hz, gyro_notchN_hz, gyro_notchN_cutoff (4.0–4.2: also
    dyn_lpf_gyro_min_hz = 0 so the static LPF applies; 3.4+: gyro_lowpass2_hz = 0); 4.3+:
    gyro_lpf1_type, gyro_lpf1_static_hz, gyro_lpf1_dyn_min_hz = 0, gyro_lpf2_static_hz = 0.
    PT2/PT3 exist from 4.3; an older version gets a comment instead.
    """
    v = tuple(version) if version else (4, 5, 0)
    kind, fc = row["filter"], row["cutoff_hz"]
    out = []
    if v >= (4, 3, 0):
        out += [
            f"set gyro_lpf1_type = {_BF_TYPE.get(kind, kind.upper())}",
            f"set gyro_lpf1_static_hz = {fc:.0f}",
            "set gyro_lpf1_dyn_min_hz = 0",
            "set gyro_lpf2_static_hz = 0",
        ]
        cut = "cutoff"
    else:
        if kind in ("pt2", "pt3"):
            out.append(f"# {kind.upper()} needs Betaflight 4.3+; this firmware has PT1 and BIQUAD")
        lp = "gyro_lowpass" if v < (3, 2, 0) else "gyro_lowpass_hz"
        out += [f"set gyro_lowpass_type = {_BF_TYPE.get(kind, kind.upper())}", f"set {lp} = {fc:.0f}"]
        if (3, 4, 0) <= v:
            out.append("set gyro_lowpass2_hz = 0")
        if (4, 0, 0) <= v:
            out.append("set dyn_lpf_gyro_min_hz = 0")
        cut = "cut" if v < (3, 2, 0) else "cutoff"
    notches = [s for s in row["stages"] if s["kind"] == "notch"]
    for i in range(2):
        if i < len(notches):
            out += [
                f"set gyro_notch{i + 1}_hz = {notches[i]['cutoff_hz']:.0f}",
                f"set gyro_notch{i + 1}_{cut} = {notches[i]['notch_cutoff_hz']:.0f}",
            ]
        else:
            out.append(f"set gyro_notch{i + 1}_hz = 0")
    return out


#: Betaflight's RPM filter notch Q: ``rpm_filter_q`` / ``gyro_rpm_notch_q`` default 500, used as
#: Q = value/100 (src/main/flight/rpm_filter.c: ``rpmFilterConfig->rpm_filter_q / 100.0f``).
RPM_NOTCH_Q = 5.0


def preview_tracking(
    f_hz: np.ndarray,
    band_psd: np.ndarray,
    band_weights: np.ndarray,
    base: Candidate,
    track_hz: np.ndarray,
    *,
    reliable_below_hz: float,
    omega_rms_rad_s: float,
    loop_scale: float = 1.0,
    rate_hz: float,
    q: float = RPM_NOTCH_Q,
    lines: Sequence[dict] = (),
) -> dict:
    """An RPM-tracking notch (Betaflight's RPM filter, one harmonic) on top of ``base``.

    The notch centre follows the line: in throttle band b it sits at ``track_hz[b, l]`` for
    each tracked line l (NaN: no notch in that band, e.g. below rpm_filter_min_hz). Each band's
    spectrum ``band_psd[b]`` (raw domain) is filtered by the chain of that band; the scores
    combine the bands with ``band_weights`` (their share of the airborne windows): noise
    powers add with the weights, delay is the weighted mean.
    """
    rows = []
    for b in range(band_psd.shape[0]):
        st = list(base.stages)
        for f0 in np.atleast_1d(track_hz[b]):
            if np.isfinite(f0) and f0 < rate_hz / 2:
                st.append(_stage("notch", f0, rate_hz, q=q, notch_cutoff_hz=float("nan")))
        c = Candidate(base.name, tuple(st), family=base.family, lowpass=base.lowpass, cutoff_hz=base.cutoff_hz)
        rows.append(
            preview(
                f_hz,
                band_psd[b],
                c,
                reliable_below_hz=reliable_below_hz,
                omega_rms_rad_s=omega_rms_rad_s,
                loop_scale=loop_scale,
                lines=lines,
            )
        )
    w = np.asarray(band_weights, float) / np.sum(band_weights)
    tau_ms = float(np.sum(w * [r["delay_ms"] for r in rows]))
    motor = float(np.sqrt(np.sum(w * np.array([r["motor_noise"] for r in rows]) ** 2)))
    gn = {a: float(np.sqrt(np.sum(w * np.array([r["gyro_noise_rad_s"][a] for r in rows]) ** 2))) for a in "xyz"}
    th_v = float(np.sqrt(np.sum(w * np.radians([r["attitude_cost_vibration_deg"] for r in rows]) ** 2)))
    th_d = tau_ms * 1e-3 * omega_rms_rad_s
    after = np.nansum(w[:, None, None] * np.array([r["psd_after"] for r in rows]), axis=0)
    name = base.name + f" + RPM notch (Q {q:g})"
    return {
        "name": name,
        "family": "betaflight",
        "filter": base.lowpass,
        "cutoff_hz": base.cutoff_hz,
        "notches_hz": [],
        "rpm_notch": {"q": q, "tracks_hz": np.asarray(track_hz, float).tolist()},
        "stages": list(base.stages),
        "delay_ms": tau_ms,
        "phase_deg_at_hz": [float(np.sum(w * [r["phase_deg_at_hz"][0] for r in rows])), rows[0]["phase_deg_at_hz"][1]],
        "gyro_noise_rad_s": gn,
        "motor_noise": motor,
        "attitude_cost": float(np.degrees(math.hypot(th_d, th_v))),
        "attitude_cost_delay_deg": float(np.degrees(th_d)),
        "attitude_cost_vibration_deg": float(np.degrees(th_v)),
        "lines_left": [],
        "psd_after": after,
    }


def band_coverage(
    band: dict, *, version: tuple | None = None, is_betaflight: bool = True, hover_throttle: float | None = None
) -> dict:
    """Firmware settings whose notch covers an energy band wherever it wanders.

    ``band``: a whole-flight energy band (:mod:`gyrocore.flight.energy_bands`) with its ``per_band``
    entries and law. Its range is the lowest lower edge to the highest upper edge over the
    throttle bands (the whole flight's edges when it has no per-band entries).

    * Betaflight dynamic notch (4.2+, ``dyn_notch_min_hz`` / ``dyn_notch_max_hz``; ranges read in
      each tag's ``cli/settings.c``: min 60–250 Hz in 4.2–4.3, 20–250 from 4.4; max 200–1000):
      the tracking range set to the band's range, clamped to the setting's limits (said when
      clamped). Older versions get a comment.
    * ArduPilot harmonic notch (``INS_HNTCH_*``, ardupilot.org "Throttle Based Dynamic Notch
      Setup"): a band that follows the throttle → MODE 1, REF = the hover throttle, FREQ = the
      law's centre there, BW = max(band width, FREQ/2); one that follows eRPM → MODE 3 (ESC
      telemetry), FREQ below the band (its range's lower edge), REF 1; a fixed band → MODE 0,
      FREQ = centre, BW = width.
    * PX4 static notch (``IMU_GYRO_NF0_FRQ`` / ``IMU_GYRO_NF0_BW``, PX4 1.13+; earlier
      ``IMU_GYRO_NF_FREQ`` / ``IMU_GYRO_NF_BW``): centre and width (a static notch: it covers
      the whole-flight band, not its wander).
    """
    edges = [band["edges_hz"]] + [p["edges_hz"] for p in band.get("per_band", [])]
    lo = float(min(e[0] for e in edges))
    hi = float(max(e[1] for e in edges))
    c, w = float(band["centre_hz"]), float(band["width_hz"])
    out = {
        "band": {
            "axis": band["axis"],
            "centre_hz": c,
            "edges_hz": band["edges_hz"],
            "width_hz": w,
            "share_of_power_above_40hz": band.get("share_of_power_above_40hz"),
            "follows": band.get("follows"),
        },
        "range_hz": [lo, hi],
    }
    if is_betaflight:
        v = tuple(version) if version else (4, 5, 0)
        if v >= (4, 2, 0):
            mn_lim = (20, 250) if v >= (4, 4, 0) else (60, 250)
            mn = int(min(max(math.floor(lo), mn_lim[0]), mn_lim[1]))
            mx = int(min(max(math.ceil(hi), 200), 1000))
            bf = [f"set dyn_notch_min_hz = {mn}", f"set dyn_notch_max_hz = {mx}"]
            if mn > lo or mx < hi:
                bf.insert(
                    0,
                    f"# the band spans {lo:.0f}-{hi:.0f} Hz; dyn_notch_min_hz takes {mn_lim[0]}-{mn_lim[1]}, "
                    f"dyn_notch_max_hz 200-1000: clamped, the notch cannot follow all of it",
                )
        else:
            bf = [
                f"# Betaflight {'.'.join(map(str, v))} has no dyn_notch_min_hz/dyn_notch_max_hz (4.2+): "
                f"the static notch above is the way to cover the band {lo:.0f}-{hi:.0f} Hz"
            ]
        out["betaflight_dynamic_notch"] = bf
    fol = band.get("follows")
    law = band.get("law") or {}
    if fol == "throttle" and not band.get("aliased") and hover_throttle is not None and "hz_per_unit" in law:
        f_h = float(law["hz_at_zero"] + law["hz_per_unit"] * hover_throttle)
        out["ardupilot"] = {
            "INS_HNTCH_ENABLE": 1,
            "INS_HNTCH_MODE": 1,
            "INS_HNTCH_REF": round(float(hover_throttle), 3),
            "INS_HNTCH_FREQ": round(f_h),
            "INS_HNTCH_BW": round(max(w, f_h / 2.0)),
        }
    elif fol == "erpm":
        out["ardupilot"] = {
            "INS_HNTCH_ENABLE": 1,
            "INS_HNTCH_MODE": 3,
            "INS_HNTCH_REF": 1,
            "INS_HNTCH_FREQ": round(lo),
            "INS_HNTCH_BW": round(max(w, lo / 2.0)),
        }
    else:
        out["ardupilot"] = {
            "INS_HNTCH_ENABLE": 1,
            "INS_HNTCH_MODE": 0,
            "INS_HNTCH_FREQ": round(c),
            "INS_HNTCH_BW": round(w),
        }
    out["px4"] = {"IMU_GYRO_NF0_FRQ": round(c, 1), "IMU_GYRO_NF0_BW": round(w, 1)}
    return out


# ------------------------------------------------------------------ the recommendation for a flight
_KEYS = ("filter", "cutoff_hz", "notches_hz", "attitude_cost", "delay_ms", "motor_noise")


def _public_row(row: dict) -> dict:
    d = {k: row[k] for k in _KEYS}
    if "rpm_notch" in row:
        d["rpm_notch"] = row["rpm_notch"]
    d["stages"] = row["stages"]
    d.update(
        {
            "name": row["name"],
            "phase_deg_at_hz": row["phase_deg_at_hz"],
            "gyro_noise_rad_s": row["gyro_noise_rad_s"],
            "attitude_cost_delay_deg": row["attitude_cost_delay_deg"],
            "attitude_cost_vibration_deg": row["attitude_cost_vibration_deg"],
            "lines_left": row["lines_left"],
            "bands_left": row.get("bands_left", []),
        }
    )
    return d


def recommend_filter(rec, *, loop_hz: float | None = None, window_s: float = 1.0, use: str = "auto") -> dict:
    """The gyro filter recommendation for a flight recording, in firmware parameter names.

    The flight's spectrum before the firmware's filters (:func:`gyrocore.flight.vibration.analyse`),
    every candidate chain previewed on it (:func:`preview`, :func:`preview_tracking` for RPM
    notches following the throttle-linked lines), the pick under the motor-noise budget
    (:func:`recommend`) and its Betaflight ``set`` lines, PX4 and ArduPilot parameters
    (``gyroharness filter``'s JSON, DESIGN.md).

    Parameters
    ----------
    rec : Recording
        A converted flight log (blackbox, ULog, DataFlash) or a simulated recording.
    loop_hz : float, optional
        Rate the gyro filters run at, Hz (default: the log header's, else the data rate).
    window_s : float
        Spectral window, s.
    use : {"auto", "prefilter", "gyro"}
        Signal (see :func:`gyrocore.flight.vibration.analyse`).

    Returns
    -------
    dict
        ``recommended``, ``as_flown``, ``firmware`` (``betaflight`` set lines, ``px4``,
        ``ardupilot``), ``defaults``, ``budget``, ``notes`` and the other keys of the ``filter``
        JSON, plus ``_rows`` (every previewed chain) and ``_res`` (the
        :class:`~gyrocore.flight.vibration.VibrationResult`).
    """
    res = analyse(rec, use=use, undo=True, window_s=window_s)
    notes = list(res.notes)
    if res.signal != "raw":
        notes.append("spectrum not fully before the firmware filters (" + res.signal + "): previews start from it")
    meta = rec.meta
    rate = loop_hz or (float(meta["gyro_filter_rate_hz"]) if "gyro_filter_rate_hz" in meta else res.rate_hz)
    ctx = _PreviewContext(res, _flight_rate_rms(rec, res.rate_hz), loop_scale(meta), rate)
    as_flown = _as_flown(meta, notes)
    bands = _notch_bands(res, notes)
    cands = candidates(rate, lines=res.lines, as_flown=as_flown, nyquist_hz=res.rate_hz / 2, bands=bands)
    rows = [ctx.preview(c, bands) for c in cands]
    moving = [ln for ln in res.lines if ln["follows"] in ("throttle", "erpm") and not ln.get("aliased")]
    rows += _rpm_tracking_rows(ctx, cands, moving, notes)
    fw = _Firmware.of(meta)
    # another firmware's RPM filter (INAV's) was not read here: its candidates are reported, not recommended
    can_rpm = fw.is_betaflight and (fw.version is None or fw.version >= (4, 0, 0))
    best, budget, src, front = recommend(rows if can_rpm else [r for r in rows if "rpm_notch" not in r])
    rpm_best = _rpm_best(rows, budget, fw, can_rpm=can_rpm, notes=notes)
    by = {r["family"]: r for r in rows}
    b2best = _butter2_best(ctx, as_flown, bands, budget)
    ardu = _ardupilot_params(b2best, moving)
    coverage = None
    if bands:
        u_hover = float(np.median([b["median"] for b in res.bands])) if res.bands else None
        coverage = band_coverage(bands[0], version=fw.version, is_betaflight=fw.is_betaflight, hover_throttle=u_hover)
        ardu = dict(ardu, **coverage["ardupilot"])  # the harmonic notch on the dominant band, not on a weaker line
    bf_lines = _betaflight_lines(best, fw, as_flown, notes)
    return {
        "recommended": _public_row(best),
        "as_flown": _public_row(by["as_flown"]) if "as_flown" in by else None,
        "with_rpm_filter": _public_row(rpm_best) if rpm_best else None,
        "firmware": {
            "betaflight": bf_lines,
            "px4": {"IMU_GYRO_CUTOFF": round(b2best["cutoff_hz"]), **(coverage["px4"] if coverage else {})},
            "ardupilot": ardu,
        },
        "defaults": {
            k: _public_row(by[k]) for k in ("betaflight_default", "px4_default", "ardupilot_default") if k in by
        },
        "article": _public_row(by["article"]),
        "px4_ardupilot_lowpass": _public_row(b2best),
        "budget": {"motor_noise": budget, "from": src},
        "pareto": front,
        "scores": {
            "attitude_cost": "deg: hypot(delay x flight-band rate rms, vibration jitter)",
            "motor_noise": "rad/s^2: rms of d/dt(filtered gyro) above 40 Hz (D-term input)",
            "delay_ms": f"mean group delay {FLIGHT_BAND_HZ[0]:g}-{FLIGHT_BAND_HZ[1]:g} Hz",
        },
        "flight_rate_rms_rad_s": ctx.omega_rms_rad_s,
        "filter_rate_hz": rate,
        "reliable_below_hz": res.reliable_below_hz,
        "vibration": {
            "signal": res.signal,
            "rms_above_40hz_rad_s": res.rms_above_40hz_rad_s,
            "lines": res.lines,
            "energy_bands": res.energy_bands,
            "dominant_vibration": res.dominant_vibration,
        },
        "band_coverage": coverage,
        "candidates": [
            {
                "name": r["name"],
                "attitude_cost": r["attitude_cost"],
                "motor_noise": r["motor_noise"],
                "delay_ms": r["delay_ms"],
            }
            for r in rows
        ],
        "notes": notes
        + [
            "open-loop spectral/delay cost model on the recorded gyro; closed loop (flown with this "
            "flight's vibration): gyroharness filter-closed-loop",
            "Betaflight 4.x default: static part only (dynamic LPF at its 250 Hz minimum + LPF2 500 Hz; dynamic notch and RPM filter not modelled)",
        ],
        "_rows": rows,
        "_res": res,
    }


# ------------------------------------------------------------------ the steps of recommend_filter
@dataclass(frozen=True)
class _PreviewContext:
    """What every candidate of one flight is previewed against."""

    res: object  # the flight's VibrationResult
    omega_rms_rad_s: float  # flight-band angular rate RMS (:func:`_flight_rate_rms`)
    loop_scale: float  # measured / nominal loop rate
    rate_hz: float  # rate the gyro filters run at

    def preview(self, c: Candidate, bands: list) -> dict:
        return preview(
            self.res.f_hz,
            self.res.mean_psd,
            c,
            reliable_below_hz=self.res.reliable_below_hz,
            omega_rms_rad_s=self.omega_rms_rad_s,
            loop_scale=self.loop_scale,
            lines=self.res.lines,
            bands=bands,
        )


def _flight_rate_rms(rec, rate_hz: float) -> float:
    """Flight-band angular rate (the attitude cost of delay): RMS of the gyro below 30 Hz, airborne, rad/s."""
    sos = signal.butter(4, FLIGHT_BAND_HZ[1], fs=rate_hz, output="sos")
    g_lp = signal.sosfiltfilt(sos, rec.gyro_rad_s, axis=0)
    air = np.ones(rec.n, bool)
    if "motor_cmd_mean" in rec.extra:
        air = rec.extra["motor_cmd_mean"] >= 0.1
    return float(np.sqrt(np.mean(np.sum(g_lp[air] ** 2, axis=1))))


def _as_flown(meta: dict, notes: list) -> list | None:
    """The filter chain the flight was flown with (its header's), or None; its dynamic stages said in ``notes``."""
    if "gyro_filters" not in meta:
        return None
    as_flown = json.loads(meta["gyro_filters"])
    dyn = [s for s in as_flown if s.get("dynamic")]
    if dyn:
        notes.append(
            "as flown: dynamic filters (" + ", ".join(s["kind"] for s in dyn) + ") not modelled, static part only"
        )
    return as_flown


def _notch_bands(res, notes: list) -> list:
    """The energy bands that carry a notch-worthy share of the rms power (gyrocore.flight.energy_bands):
    the static-notch candidates sit on them first, each chain says how much of their power it lets through."""
    bands = [
        b
        for b in res.energy_bands
        if (b.get("share_of_power_above_40hz") or 0.0) >= BAND_NOTCH_MIN_SHARE and not b.get("aliased")
    ]
    if bands:
        targets = notch_targets(res.lines, bands, nyquist_hz=res.rate_hz / 2)
        notes.append(
            "static notch candidates at the energy band(s) "
            + ", ".join(
                f"{b['axis']} {b['edges_hz'][0]:.0f}-{b['edges_hz'][1]:.0f} Hz ({100 * b['share_of_power_above_40hz']:.0f} % of the "
                f"rms power above 40 Hz)"
                for b in bands
            )
            + "; notch targets: "
            + ", ".join(t[2] for t in targets)
        )
    return bands


def _rpm_tracking_rows(ctx: _PreviewContext, cands: list, moving: list, notes: list) -> list:
    """RPM-tracking notch (needs eRPM telemetry in flight): one notch per moving line, at its
    frequency in each throttle band, on top of each low-pass of the grid."""
    res = ctx.res
    if not moving or res.band_psd.shape[0] <= 1:
        return []
    us = np.array([b["median"] for b in res.bands])
    track = np.column_stack([ln["law"]["hz_at_zero"] + ln["law"]["hz_per_unit"] * us for ln in moving[:3]])
    track[track < 100.0] = np.nan  # rpm_filter_min_hz default 100
    weights = np.array([b["n_windows"] for b in res.bands], float)
    rows = [
        preview_tracking(
            res.f_hz,
            res.band_psd,
            weights,
            c,
            track,
            reliable_below_hz=res.reliable_below_hz,
            omega_rms_rad_s=ctx.omega_rms_rad_s,
            loop_scale=ctx.loop_scale,
            rate_hz=ctx.rate_hz,
            lines=res.lines,
        )
        for c in cands
        if c.family == "betaflight" and c.lowpass in LP_KINDS and not c.notches_hz
    ]
    notes.append(
        f"RPM-tracking notch candidates: Q {RPM_NOTCH_Q:g} notches following "
        + ", ".join(f"{ln['axis']} {ln['frequency_hz']:.0f} Hz" for ln in moving[:3])
        + " per throttle band (needs bidirectional DShot / eRPM)"
    )
    return rows


@dataclass(frozen=True)
class _Firmware:
    """The firmware that flew the log: its name, whether it is Betaflight, its Betaflight version."""

    name: str
    is_betaflight: bool
    version: tuple | None
    version_str: str

    @classmethod
    def of(cls, meta: dict) -> _Firmware:
        name = str(meta.get("firmware_name", "betaflight")).lower()
        is_bf = name == "betaflight"
        version = (
            tuple(int(x) for x in meta["firmware_version"].split(".")) if "firmware_version" in meta and is_bf else None
        )
        return cls(name, is_bf, version, str(meta.get("firmware_version", "")))


def _rpm_best(rows: list, budget: float, fw: _Firmware, *, can_rpm: bool, notes: list) -> dict | None:
    """The best RPM-filter chain under the motor-noise budget (the quietest when none meets it);
    where the firmware cannot fly it, said in ``notes``."""
    rpm_rows = [r for r in rows if "rpm_notch" in r]
    if not rpm_rows:
        return None
    ok_r = [r for r in rpm_rows if r["motor_noise"] <= budget * (1 + 1e-9)] or [
        min(rpm_rows, key=lambda r: r["motor_noise"])
    ]
    if not can_rpm:
        notes.append(
            (
                f"RPM filter: Betaflight {fw.version_str} has none (4.0+ with bidirectional DShot); "
                if fw.is_betaflight
                else f"RPM filter: {fw.name}'s was not read here; "
            )
            + "its best candidate is reported under 'with_rpm_filter', not recommended"
        )
    return min(ok_r, key=lambda r: r["attitude_cost"])


def _butter2_best(ctx: _PreviewContext, as_flown: list | None, bands: list, budget: float) -> dict:
    """PX4 / ArduPilot: their LPF is a 2nd-order Butterworth; the best cutoff under the same budget.

    The grid, plus the flown 2nd-order Butterworth cutoff (ArduPilot INS_GYRO_FILTER, PX4
    IMU_GYRO_CUTOFF): without it an ArduPilot log whose own 42 Hz was best was told "40" (at
    the flown stage's own rate, the same chain as the "as flown" row).
    """
    flown_b2 = {
        float(st["cutoff_hz"]): st
        for st in (as_flown or [])
        if st.get("kind") == "butter2" and not st.get("dynamic") and st.get("cutoff_hz")
    }
    b2 = []
    for fc in sorted(set(CUTOFF_GRID_HZ + (20.0, 30.0)) | set(flown_b2)):
        if fc not in flown_b2 and fc * 2.0 >= ctx.rate_hz / 2:
            # the grid's rule in candidates(): a cutoff at or above a quarter of the filter rate is
            # not designed (a PX4 ULog's 250-Hz sensor_combined: 140 Hz was above its Nyquist)
            continue
        st = (
            _stage("butter2", fc, float(flown_b2[fc].get("rate_hz") or ctx.rate_hz))
            if fc in flown_b2
            else _stage("butter2", fc, ctx.rate_hz)
        )
        c = Candidate(f"butter2 {fc:g} Hz", (st,), family="butter2", lowpass="butter2", cutoff_hz=fc)
        b2.append(ctx.preview(c, bands))
    ok = [r for r in b2 if r["motor_noise"] <= budget * (1 + 1e-9)] or [min(b2, key=lambda r: r["motor_noise"])]
    return min(ok, key=lambda r: r["attitude_cost"])


def _ardupilot_params(b2best: dict, moving: list) -> dict:
    """ArduPilot's gyro low-pass and, with a moving line, its harmonic notch on the strongest."""
    ardu = {"INS_GYRO_FILTER": round(b2best["cutoff_hz"])}
    if moving:
        top = max(moving, key=lambda ln: ln["amplitude_rad_s"])
        span = [p["frequency_hz"] for p in top.get("per_band", [])] or [top["frequency_hz"]]
        ardu.update(
            {
                "INS_HNTCH_ENABLE": 1,
                "INS_HNTCH_MODE": 1,
                "INS_HNTCH_FREQ": round(min(span)),
                "INS_HNTCH_BW": round(max(40.0, min(span) / 2)),
            }
        )
    return ardu


def _betaflight_lines(best: dict, fw: _Firmware, as_flown: list | None, notes: list) -> list[str]:
    """The Betaflight CLI ``set`` lines of the pick (a comment for another firmware), with a
    warning where they turn off the dynamic low-pass that was flown, and the RPM filter's lines."""
    if not fw.is_betaflight:
        return [f"# {fw.name} log: Betaflight CLI names do not apply (this firmware's parameter names were not read)"]
    bf_lines = betaflight_cli(best, fw.version)
    flown_dyn_lpf = [st for st in (as_flown or []) if st.get("kind") == "dyn_lpf"]
    if flown_dyn_lpf and any(ln.endswith("dyn_min_hz = 0") or ln == "set dyn_lpf_gyro_min_hz = 0" for ln in bf_lines):
        d = flown_dyn_lpf[0]
        msg = (
            f"the set lines turn off the dynamic gyro low-pass you flew ({d['cutoff_hz']:g}-{d.get('max_hz') or float('nan'):g} Hz), "
            f"which the figures above do not model (the 'as flown' row and the motor-noise budget are its static part "
            f"only, so the recommendation may filter less than you fly now): keep your dyn_lpf settings unless you "
            f"mean to change them"
        )
        notes.append(msg)
        bf_lines.insert(0, "# " + msg)
    if "rpm_notch" in best:
        v = fw.version or (4, 5, 0)
        if v < (4, 0, 0):
            bf_lines.append("# the RPM filter needs Betaflight 4.0+ with bidirectional DShot (eRPM telemetry)")
        elif v < (4, 3, 0):
            bf_lines += [
                "set dshot_bidir = ON",
                "set gyro_rpm_notch_harmonics = 1",
                f"set gyro_rpm_notch_q = {RPM_NOTCH_Q * 100:.0f}",
            ]
        else:
            bf_lines += [
                "set dshot_bidir = ON",
                "set rpm_filter_harmonics = 1",
                f"set rpm_filter_q = {RPM_NOTCH_Q * 100:.0f}",
            ]
    return bf_lines
