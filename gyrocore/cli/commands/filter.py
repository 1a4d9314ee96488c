"""``gyroharness filter FILE``: choose the gyro filter from the pilot's own spectrum (DESIGN.md).

JSON: ``{"recommended": {"filter", "cutoff_hz", "notches_hz", "attitude_cost", "delay_ms",
"motor_noise", ...}, "as_flown": {same keys}, "firmware": {"betaflight": ["set …", ...],
"px4": {...}, "ardupilot": {...}}, "defaults": {...}, "article": {...}, "pareto": [...], ...}``.
First version: the open-loop spectral / delay cost model of :mod:`gyrocore.flight.preview` on the
recorded gyro (before the firmware's filters); the closed-loop comparison (the candidates flown
with the flight's vibration by the simulator) is ``gyroharness filter-closed-loop``.
"""

from __future__ import annotations

import math
import os

import click
import numpy as np

from gyrocore.cli import emit_json
from gyrocore.errors import GyroInputError, warn_repair

_KEYS = ("filter", "cutoff_hz", "notches_hz", "attitude_cost", "delay_ms", "motor_noise")


def _public(row: dict) -> dict:
    d = {k: row[k] for k in _KEYS}
    if "rpm_notch" in row:
        d["rpm_notch"] = row["rpm_notch"]
    d["stages"] = row["stages"]
    d.update({"name": row["name"], "phase_deg_at_hz": row["phase_deg_at_hz"], "gyro_noise_rad_s": row["gyro_noise_rad_s"],
              "attitude_cost_delay_deg": row["attitude_cost_delay_deg"],
              "attitude_cost_vibration_deg": row["attitude_cost_vibration_deg"], "lines_left": row["lines_left"],
              "bands_left": row.get("bands_left", [])})
    return d


def run_filter(rec, *, loop_hz: float | None = None, window_s: float = 1.0, use: str = "auto") -> dict:
    """Recommendation for a recording (see the module docstring); returns the JSON dict."""
    from scipy import signal

    from gyrocore.flight import preview as P
    from gyrocore.flight.vibration import analyse

    res = analyse(rec, use=use, undo=True, window_s=window_s)
    notes = list(res.notes)
    if res.signal != "raw":
        notes.append("spectrum not fully before the firmware filters (" + res.signal + "): previews start from it")
    meta = rec.meta
    rate = loop_hz or (float(meta["gyro_filter_rate_hz"]) if "gyro_filter_rate_hz" in meta else res.rate_hz)
    loop_scale = 1.0
    try:
        ls = float(meta["loop_rate_measured_hz"]) / float(meta["pid_rate_hz"])
        loop_scale = ls if np.isfinite(ls) and 0.5 < ls < 2 else 1.0
    except (KeyError, ValueError):
        pass
    # flight-band angular rate (the attitude cost of delay): RMS of the gyro below 30 Hz, airborne
    sos = signal.butter(4, P.FLIGHT_BAND_HZ[1], fs=res.rate_hz, output="sos")
    g_lp = signal.sosfiltfilt(sos, rec.gyro_rad_s, axis=0)
    air = np.ones(rec.n, bool)
    if "motor_cmd_mean" in rec.extra:
        air = rec.extra["motor_cmd_mean"] >= 0.1
    omega_rms = float(np.sqrt(np.mean(np.sum(g_lp[air] ** 2, axis=1))))
    as_flown = None
    if "gyro_filters" in meta:
        import json

        as_flown = json.loads(meta["gyro_filters"])
        dyn = [s for s in as_flown if s.get("dynamic")]
        if dyn:
            notes.append("as flown: dynamic filters (" + ", ".join(s["kind"] for s in dyn) + ") not modelled, static part only")
    # the energy bands that carry a notch-worthy share of the rms power (gyrocore.flight.energy_bands): the
    # static-notch candidates sit on them first, each chain says how much of their power it lets through
    bands = [b for b in res.energy_bands
             if (b.get("share_of_power_above_40hz") or 0.0) >= P.BAND_NOTCH_MIN_SHARE and not b.get("aliased")]
    cands = P.candidates(rate, lines=res.lines, as_flown=as_flown, nyquist_hz=res.rate_hz / 2, bands=bands)
    targets = P.notch_targets(res.lines, bands, nyquist_hz=res.rate_hz / 2)
    if bands:
        notes.append("static notch candidates at the energy band(s) " + ", ".join(
            f"{b['axis']} {b['edges_hz'][0]:.0f}-{b['edges_hz'][1]:.0f} Hz ({100 * b['share_of_power_above_40hz']:.0f} % of the "
            f"rms power above 40 Hz)" for b in bands) + "; notch targets: " + ", ".join(t[2] for t in targets))
    rows = [P.preview(res.f_hz, res.mean_psd, c, reliable_below_hz=res.reliable_below_hz, omega_rms_rad_s=omega_rms,
                      loop_scale=loop_scale, lines=res.lines, bands=bands) for c in cands]
    # RPM-tracking notch (needs eRPM telemetry in flight): one notch per moving line, at its
    # frequency in each throttle band, on top of each low-pass of the grid
    moving = [ln for ln in res.lines if ln["follows"] in ("throttle", "erpm") and not ln.get("aliased")]
    if moving and res.band_psd.shape[0] > 1:
        us = np.array([b["median"] for b in res.bands])
        track = np.column_stack([ln["law"]["hz_at_zero"] + ln["law"]["hz_per_unit"] * us for ln in moving[:3]])
        track[track < 100.0] = np.nan  # rpm_filter_min_hz default 100
        weights = np.array([b["n_windows"] for b in res.bands], float)
        for c in [c for c in cands if c.family == "betaflight" and c.lowpass in P.LP_KINDS and not c.notches_hz]:
            rows.append(P.preview_tracking(res.f_hz, res.band_psd, weights, c, track, reliable_below_hz=res.reliable_below_hz,
                                           omega_rms_rad_s=omega_rms, loop_scale=loop_scale, rate_hz=rate, lines=res.lines))
        notes.append(f"RPM-tracking notch candidates: Q {P.RPM_NOTCH_Q:g} notches following " + ", ".join(
            f"{ln['axis']} {ln['frequency_hz']:.0f} Hz" for ln in moving[:3]) + " per throttle band (needs bidirectional DShot / eRPM)")
    firmware = str(meta.get("firmware_name", "betaflight")).lower()
    is_bf = firmware == "betaflight"
    version = tuple(int(x) for x in meta["firmware_version"].split(".")) if "firmware_version" in meta and is_bf else None
    rpm_rows = [r for r in rows if "rpm_notch" in r]
    # another firmware's RPM filter (INAV's) was not read here: its candidates are reported, not recommended
    can_rpm = is_bf and (version is None or version >= (4, 0, 0))
    best, budget, src, front = P.recommend(rows if can_rpm else [r for r in rows if "rpm_notch" not in r])
    rpm_best = None
    if rpm_rows:
        ok_r = [r for r in rpm_rows if r["motor_noise"] <= budget * (1 + 1e-9)] or [min(rpm_rows, key=lambda r: r["motor_noise"])]
        rpm_best = min(ok_r, key=lambda r: r["attitude_cost"])
        if not can_rpm:
            notes.append((f"RPM filter: Betaflight {meta['firmware_version']} has none (4.0+ with bidirectional DShot); "
                          if is_bf else f"RPM filter: {firmware}'s was not read here; ")
                         + "its best candidate is reported under 'with_rpm_filter', not recommended")
    by = {r["family"]: r for r in rows}
    # PX4 / ArduPilot: their LPF is a 2nd-order Butterworth; best cutoff under the same budget
    b2 = []
    # the grid, plus the flown 2nd-order Butterworth cutoff (ArduPilot INS_GYRO_FILTER, PX4
    # IMU_GYRO_CUTOFF): without it an ArduPilot log whose own 42 Hz was best was told "40"
    # (at the flown stage's own rate, the same chain as the "as flown" row)
    flown_b2 = {float(st["cutoff_hz"]): st for st in (as_flown or [])
                if st.get("kind") == "butter2" and not st.get("dynamic") and st.get("cutoff_hz")}
    for fc in sorted(set(P.CUTOFF_GRID_HZ + (20.0, 30.0)) | set(flown_b2)):
        st = P._stage("butter2", fc, float(flown_b2[fc].get("rate_hz") or rate)) if fc in flown_b2 else P._stage("butter2", fc, rate)
        c = P.Candidate(f"butter2 {fc:g} Hz", (st,), family="butter2", lowpass="butter2", cutoff_hz=fc)
        b2.append(P.preview(res.f_hz, res.mean_psd, c, reliable_below_hz=res.reliable_below_hz, omega_rms_rad_s=omega_rms,
                            loop_scale=loop_scale, lines=res.lines, bands=bands))
    ok = [r for r in b2 if r["motor_noise"] <= budget * (1 + 1e-9)] or [min(b2, key=lambda r: r["motor_noise"])]
    b2best = min(ok, key=lambda r: r["attitude_cost"])
    ardu = {"INS_GYRO_FILTER": round(b2best["cutoff_hz"])}
    if moving:
        top = max(moving, key=lambda ln: ln["amplitude_rad_s"])
        span = [p["frequency_hz"] for p in top.get("per_band", [])] or [top["frequency_hz"]]
        ardu.update({"INS_HNTCH_ENABLE": 1, "INS_HNTCH_MODE": 1, "INS_HNTCH_FREQ": round(min(span)),
                     "INS_HNTCH_BW": round(max(40.0, min(span) / 2))})
    coverage = None
    if bands:
        u_hover = float(np.median([b["median"] for b in res.bands])) if res.bands else None
        coverage = P.band_coverage(bands[0], version=version, is_betaflight=is_bf, hover_throttle=u_hover)
        ardu = dict(ardu, **coverage["ardupilot"])  # the harmonic notch on the dominant band, not on a weaker line
    bf_lines = P.betaflight_cli(best, version) if is_bf else [
        f"# {firmware} log: Betaflight CLI names do not apply (this firmware's parameter names were not read)"]
    flown_dyn_lpf = [st for st in (as_flown or []) if st.get("kind") == "dyn_lpf"]
    if is_bf and flown_dyn_lpf and any(ln.endswith("dyn_min_hz = 0") or ln == "set dyn_lpf_gyro_min_hz = 0" for ln in bf_lines):
        d = flown_dyn_lpf[0]
        msg = (f"the set lines turn off the dynamic gyro low-pass you flew ({d['cutoff_hz']:g}-{d.get('max_hz') or float('nan'):g} Hz), "
               f"which the figures above do not model (the 'as flown' row and the motor-noise budget are its static part "
               f"only, so the recommendation may filter less than you fly now): keep your dyn_lpf settings unless you "
               f"mean to change them")
        notes.append(msg)
        bf_lines.insert(0, "# " + msg)
    if "rpm_notch" in best and is_bf:
        v = version or (4, 5, 0)
        if v < (4, 0, 0):
            bf_lines.append("# the RPM filter needs Betaflight 4.0+ with bidirectional DShot (eRPM telemetry)")
        elif v < (4, 3, 0):
            bf_lines += ["set dshot_bidir = ON", "set gyro_rpm_notch_harmonics = 1", f"set gyro_rpm_notch_q = {P.RPM_NOTCH_Q * 100:.0f}"]
        else:
            bf_lines += ["set dshot_bidir = ON", "set rpm_filter_harmonics = 1", f"set rpm_filter_q = {P.RPM_NOTCH_Q * 100:.0f}"]
    out = {
        "recommended": _public(best),
        "as_flown": _public(by["as_flown"]) if "as_flown" in by else None,
        "with_rpm_filter": _public(rpm_best) if rpm_best else None,
        "firmware": {
            "betaflight": bf_lines,
            "px4": {"IMU_GYRO_CUTOFF": round(b2best["cutoff_hz"]), **(coverage["px4"] if coverage else {})},
            "ardupilot": ardu,
        },
        "defaults": {k: _public(by[k]) for k in ("betaflight_default", "px4_default", "ardupilot_default") if k in by},
        "article": _public(by["article"]),
        "px4_ardupilot_lowpass": _public(b2best),
        "budget": {"motor_noise": budget, "from": src},
        "pareto": front,
        "scores": {"attitude_cost": "deg: hypot(delay x flight-band rate rms, vibration jitter)",
                   "motor_noise": "rad/s^2: rms of d/dt(filtered gyro) above 40 Hz (D-term input)",
                   "delay_ms": f"mean group delay {P.FLIGHT_BAND_HZ[0]:g}-{P.FLIGHT_BAND_HZ[1]:g} Hz"},
        "flight_rate_rms_rad_s": omega_rms, "filter_rate_hz": rate, "reliable_below_hz": res.reliable_below_hz,
        "vibration": {"signal": res.signal, "rms_above_40hz_rad_s": res.rms_above_40hz_rad_s, "lines": res.lines,
                      "energy_bands": res.energy_bands, "dominant_vibration": res.dominant_vibration},
        "band_coverage": coverage,
        "candidates": [{"name": r["name"], "attitude_cost": r["attitude_cost"], "motor_noise": r["motor_noise"],
                        "delay_ms": r["delay_ms"]} for r in rows],
        "notes": notes + ["open-loop spectral/delay cost model on the recorded gyro; closed loop (flown with this "
                          "flight's vibration): gyroharness filter-closed-loop",
                          "Betaflight 4.x default: static part only (dynamic LPF at its 250 Hz minimum + LPF2 500 Hz; dynamic notch and RPM filter not modelled)"],
        "_rows": rows, "_res": res,
    }
    return out


def plot_filter(out: dict, path: str) -> None:
    """Gyro PSD after the recommended, as-flown, default and article chains, (°/s)²/Hz, one scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gyrocore.data.recording import atomic_open

    res = out["_res"]
    rows = {r["name"]: r for r in out["_rows"]}
    f = res.f_hz
    conv = (180 / math.pi) ** 2
    show = [("none", "k", "before firmware filters")]
    show.append((out["recommended"]["name"], "tab:green", "recommended"))
    if out["as_flown"]:
        show.append(("as flown", "tab:blue", "as flown"))
    show += [("betaflight 4.x default (static part)", "tab:orange", None), ("px4 default IMU_GYRO_CUTOFF 40", "tab:purple", None),
             ("article 1st-order 30 Hz", "tab:red", None)]
    fig, axs = plt.subplots(1, 3, figsize=(15, 4.5), constrained_layout=True)
    for j, a in enumerate("xyz"):
        ax = axs[j]
        for name, col, lab in show:
            if name in rows:
                r = rows[name]
                rec_name = out["recommended"]["name"]
                same = lab == "as flown" and rec_name in rows and np.allclose(rows[rec_name]["psd_after"], r["psd_after"])
                ax.semilogy(f, r["psd_after"][:, j] * conv, color=col, lw=0.8, ls="--" if same else "-",
                            label=f"{lab or name}{' (= recommended)' if same else ''}: {r['delay_ms']:.2f} ms, "
                                  f"motor noise {r['motor_noise']:.0f} rad/s^2")
        if res.reliable_below_hz < f[-1]:
            ax.axvspan(res.reliable_below_hz, f[-1], color="0.85", zorder=0,
                       label=f"above {res.reliable_below_hz:.0f} Hz: folded from above the logged Nyquist (unreliable)")
        ax.set_title(f"gyro {a}")
        ax.set_xlabel("frequency, Hz")
        ax.set_ylabel("PSD, (deg/s)^2/Hz")
        ax.set_ylim(1e-6, None)
        if j == 0:
            ax.legend(fontsize=6)
    fig.suptitle(f"{os.path.basename(str(out.get('file', '')))}: the flight's gyro spectrum ({res.signal} signal) "
                 f"after each candidate filter chain", fontsize=9)
    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=110)
    plt.close(fig)


@click.command("filter")
@click.argument("path", metavar="FILE", type=click.Path(path_type=str))
@click.option("--loop-hz", type=float, default=None, help="Rate the gyro filters run at (default: the log header's, else the data rate).")
@click.option("--window-s", type=float, default=1.0, show_default=True, help="Spectral window, s.")
@click.option("--signal", "use", type=click.Choice(["auto", "prefilter", "gyro"]), default="auto", show_default=True)
@click.option("--log-index", type=int, default=None, help="blackbox: only this log of the file.")
@click.option("--plot", default=None, type=click.Path(path_type=str), help="PNG of the spectra after the chains.")
@click.option("--force", is_flag=True, default=False, help="Overwrite an existing plot.")
@click.option("--json", "as_json", is_flag=True, default=False, help="Print the JSON result on stdout.")
def command(path, loop_hz, window_s, use, log_index, plot, force, as_json):
    """Recommend a gyro filter from a flight's own spectrum, beside what was flown and the firmware defaults."""
    from gyrocore.readers.convert import detect_format, load_any
    from gyrocore.data.recording import read_csv

    if plot and os.path.exists(plot) and not force:
        raise GyroInputError(f"{plot} exists; pass --force to overwrite it")
    fmt = detect_format(path)
    if log_index is not None and fmt != "blackbox":
        raise GyroInputError("--log-index applies to blackbox logs only")
    rec = load_any(path, format="blackbox", log_index=log_index) if fmt == "blackbox" else (read_csv(path) if fmt == "csv" else load_any(path))
    out = run_filter(rec, loop_hz=loop_hz, window_s=window_s, use=use)
    for w in out["_res"].warnings:
        warn_repair(w)
    out["file"] = path
    if plot:
        plot_filter(out, plot)
        out["plot"] = plot
    out = {k: v for k, v in out.items() if not k.startswith("_")}
    if as_json:
        emit_json(out)
        return
    r = out["recommended"]
    click.echo(f"recommended: {r['name']}: attitude cost {r['attitude_cost']:.3f} deg, delay {r['delay_ms']:.2f} ms, "
               f"motor noise {r['motor_noise']:.0f} rad/s^2 (budget {out['budget']['motor_noise']:.0f}, {out['budget']['from']})")
    if out["as_flown"]:
        a = out["as_flown"]
        click.echo(f"as flown:    {a['name']}: attitude cost {a['attitude_cost']:.3f} deg, delay {a['delay_ms']:.2f} ms, motor noise {a['motor_noise']:.0f}")
    for k, d in out["defaults"].items():
        click.echo(f"{k}: {d['name']}: cost {d['attitude_cost']:.3f} deg, delay {d['delay_ms']:.2f} ms, motor noise {d['motor_noise']:.0f}")
    a = out["article"]
    click.echo(f"article:     {a['name']}: cost {a['attitude_cost']:.3f} deg, delay {a['delay_ms']:.2f} ms, motor noise {a['motor_noise']:.0f}")
    click.echo("betaflight CLI:")
    for line in out["firmware"]["betaflight"]:
        click.echo("  " + line)
    click.echo("px4: " + ", ".join(f"{k} {v}" for k, v in out["firmware"]["px4"].items()))
    click.echo("ardupilot: " + ", ".join(f"{k} {v}" for k, v in out["firmware"]["ardupilot"].items()))
    for n in out.get("notes", []):  # the caveats (signal already filtered, dynamic filters not modelled)
        click.echo(f"note: {n}")
