"""The firmware's filtered gyro in simulated flight held against a real log's.

For a real flight log that carries its unfiltered gyro (``gyro_prefilter_*``: Betaflight's
``DEBUG_GYRO_SCALED``) beside the filtered one (``gyroADC``, what its PID used):

1. the log is split in halves; the vibration spec that drives the simulation is built from the
   first half's unfiltered gyro (:func:`gyrocore.vibration.analyse`, 8 equal-count throttle bands,
   as ``gyroharness vibration LOG -o SPEC``);
2. per throttle band, the vehicle class flies a hover with the firmware in the loop
   (:func:`experiments.firmware_fly.fly`), booted with the log's own tune (its header's settings,
   through the bridge: filters, dynamic notch, RPM filter, dynamic LPF, PIDs, rates) and the band's
   vibration (:func:`sim.spec_vibration.spec_injection`: the rotor line through the rotors'
   unbalance, the rest of the band as the gyro's shaped vibration);
3. the firmware's filtered gyro is logged as the log logs it (every ``P interval``-th loop, no
   anti-alias filter) and compared with the log's filtered gyro of the same band — **held out**:
   the second half (the spec never saw it) first, in sample (the first half) second — by
   :func:`gyrocore.flight.synthesis.fidelity`: per axis the RMS above 40 Hz of both and the in-band
   fraction (share of the PSD bins 40 Hz .. Nyquist where the simulated PSD is statistically
   indistinguishable from the real one; 0.95 for a perfect match).

    gyroharness firmware fidelity LOG00037.BFL [--vehicle racing5] [--duration-s 5] [--inject-to-nyquist]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import tempfile

import numpy as np
from experiments.firmware_fly import fly, settings_lines_from
from gyrocore.data.recording import read_csv, Recording
from gyrocore.errors import GyroInputError
from gyrocore.flight.synthesis import fidelity
from gyrocore.flight.vibration import analyse, write_spec
from gyrocore.readers.convert import detect_format, load_any
from sim.fw_flight import FwFlightOptions, motor_law
from sim.spec_vibration import spec_injection
from sim.vehicles import get_vehicle

__all__ = ["run", "sim_recording"]


def sim_recording(log, every: int):
    """The firmware's filtered gyro as the firmware's blackbox would log it: every ``every``-th
    loop (no anti-alias filter), as a data file whose gyro is that signal."""
    k = slice(0, None, int(every))
    return Recording(
        t_s=log.t_s[k], gyro_rad_s=log.fw_gyro_rad_s[k], meta={"gyro_signal": "filtered (firmware in the loop)"}
    )


def run(
    *,
    flight: str,
    vehicle: str = "racing5",
    seed: int = 0,
    duration_s: float = 6.0,
    settle_s: float = 1.0,
    n_calib: int = 16,
    calib_s: float = 2.0,
    bands=None,
    binary=None,
    out_dir: str | None = None,
    settings=None,
    at_band_throttle: bool = False,
    inject_to_nyquist: bool = False,
) -> dict:
    """Fidelity per throttle band (module docstring). Returns ``{"flight", "vehicle", "firmware",
    "settings_applied", "settings_skipped", "t_split_s", "bands": [{"band", "throttle",
    "held_out": fid, "in_sample": fid, "log_rms_above_40hz_rad_s", ...}]}`` with ``fid`` per axis
    as :func:`gyrocore.flight.synthesis.fidelity`."""
    rec = read_csv(flight) if detect_format(flight) == "csv" else load_any(flight)
    if "gyro_prefilter_x_rad_s" not in rec.extra:
        raise GyroInputError(
            f"{flight}: no unfiltered gyro logged (Betaflight debug_mode GYRO_SCALED): "
            "nothing to build the vibration from"
        )
    every = int(round(float(rec.meta.get("gyro_rate_hz", 8000)) / float(rec.meta.get("log_rate_nominal_hz", 1000))))
    t = rec.t_s
    t_mid = float(t[0] + 0.5 * (t[-1] - t[0]))
    # the unfiltered gyro (a partly filtered one with its known filters undone: better_tune.BBL logs after a PT1)
    raw_a = analyse(rec, use="prefilter", undo=True, t_to_s=t_mid)
    edges = [b["throttle"][0] for b in raw_a.bands] + [raw_a.bands[-1]["throttle"][1]]
    filt_a = analyse(rec, use="gyro", undo=False, t_to_s=t_mid, band_edges=edges)
    filt_b = analyse(rec, use="gyro", undo=False, t_from_s=t_mid, band_edges=edges)
    d = out_dir or tempfile.mkdtemp(prefix="fwfid_")
    os.makedirs(d, exist_ok=True)
    spec_raw = write_spec(raw_a, os.path.join(d, "spec_raw_first_half.json"), source=f"{flight} t < {t_mid:.2f} s")
    spec_fa = write_spec(
        filt_a, os.path.join(d, "spec_filtered_first_half.json"), source=f"{flight} gyroADC t < {t_mid:.2f} s"
    )
    spec_fb = write_spec(
        filt_b, os.path.join(d, "spec_filtered_second_half.json"), source=f"{flight} gyroADC t >= {t_mid:.2f} s"
    )
    settings = settings_lines_from(flight) if settings is None else list(settings)
    spec_inj = spec_raw
    if inject_to_nyquist:
        # trust the reconstruction to the logged Nyquist: the band's PSD above the spec's reliable
        # limit (where undoing the logged filters also scales content folded from above Nyquist)
        # enters at the logged frequencies, so the simulated chain filters it where the log shows it
        spec_inj = dict(spec_raw, reconstructed_reliable_below_hz=float(spec_raw["f_hz"][-1]))
    b_index = {round(b["throttle"][0], 9): j for j, b in enumerate(spec_fb["bands"])}
    rows, label, skipped, sps = [], None, [], []
    for i, b in enumerate(spec_raw["bands"]):
        if bands is not None and i not in bands:
            continue
        j = b_index.get(round(b["throttle"][0], 9))
        hover_u = None
        if at_band_throttle and b.get("median") is not None and float(b["median"]) > _own_hover_u(vehicle):
            # fly at the band's own motor command (a payload: the rotors, their line, the RPM filter,
            # the dynamic notch and LPF where the log had them); the whole band shaped, rotors balanced
            hover_u = float(b["median"])
        hv = info = None
        if hover_u is None:
            try:
                hv, over, info = spec_injection(
                    spec_inj, band=i, vehicle=vehicle, physics=True, seed=seed, n_calib=n_calib, calib_s=calib_s
                )
                how = "rotor line through the rotors' unbalance + the rest of the band shaped"
            except GyroInputError as exc:
                if "no line that follows throttle" not in str(exc):
                    raise
        if info is None:
            # at the band's throttle, or no rotor line law in this half (one throttle, no eRPM): the
            # whole band as the gyro's shaped vibration, the rotors balanced (else a line comes twice)
            _, over, info = spec_injection(spec_inj, band=i, vehicle=vehicle, physics=False, seed=seed)
            hv = False
            how = "the whole band shaped, rotors balanced, " + (
                f"hover at the band's command u = {hover_u:.3f}"
                if hover_u is not None
                else "no rotor line law in the spec"
            )
        opts = FwFlightOptions(
            scenario="hover",
            vehicle=vehicle,
            duration_s=duration_s,
            seed=seed,
            settle_s=settle_s,
            vibration=hv,
            gyro_overrides=over,
            hover_command=hover_u,
        )
        log, finfo = fly(opts, lenient=settings, binary=binary)
        label, skipped = finfo["firmware"], finfo["skipped_settings"]
        sps.append(finfo["sim_s_per_wall_s"])
        sim = analyse(sim_recording(log, every), use="gyro", undo=False, t_from_s=settle_s)
        row = {
            "band": i,
            "throttle": b["throttle"],
            "n_windows_first": b["n_windows"],
            "hover_command": hover_u,
            "log_first_vs_second_half": _repeatability(spec_fa, i, spec_fb, j) if j is not None else None,
            "in_sample": fidelity(sim, spec_fa, band=i),
            "held_out": fidelity(sim, spec_fb, band=j) if j is not None else None,
            "n_windows_second": spec_fb["bands"][j]["n_windows"] if j is not None else 0,
            "sim_mean_motor": float(np.mean(log.motors[log.t_s >= settle_s])),
            "sim_rotor_hz": float(np.mean(log.rotor_speed_rad_s[log.t_s >= settle_s]) / (2 * math.pi)),
            "injection": how,
            "physics": info.get("physics"),
            "rms_by_range": _rms_by_range(sim, spec_fb, j) if j is not None else None,
        }
        rows.append(row)
    return {
        "flight": flight,
        "vehicle": vehicle,
        "firmware": label,
        "seed": seed,
        "duration_s": duration_s,
        "inject_to_nyquist": inject_to_nyquist,
        "at_band_throttle": at_band_throttle,
        "spec_reliable_below_hz": spec_raw.get("reconstructed_reliable_below_hz"),
        "log_every": every,
        "t_split_s": t_mid,
        "settings_applied": settings,
        "settings_skipped": skipped,
        "sim_s_per_wall_s": float(np.median(sps)) if sps else math.nan,
        "bands": rows,
        "specs": {
            "raw_first_half": os.path.join(d, "spec_raw_first_half.json"),
            "filtered_first_half": os.path.join(d, "spec_filtered_first_half.json"),
            "filtered_second_half": os.path.join(d, "spec_filtered_second_half.json"),
        },
    }


#: frequency ranges of :func:`_rms_by_range`, Hz: the flight's low vibration band, the band of
#: the static notches and rotor lines of a small quad, and the top up to the logged Nyquist
RANGES_HZ = ((40.0, 150.0), (150.0, 300.0), (300.0, 500.0))


def _rms_by_range(sim, spec: dict, band: int) -> dict:
    """RMS of the simulated and the real (held-out) filtered gyro in :data:`RANGES_HZ`, per axis, rad/s:
    where the two spectra part."""
    b = spec["bands"][band]
    f_r = np.asarray(spec["f_hz"], float)
    out = {}
    for lo, hi in RANGES_HZ:
        key = f"{lo:g}-{hi:g}"
        out[key] = {}
        for j, a in enumerate("xyz"):
            real = np.array([np.nan if v is None else v for v in b["psd_rad2_s2_hz"][a]], float)
            sel_r = (f_r >= lo) & (f_r < hi)
            sel_s = (sim.f_hz >= lo) & (sim.f_hz < hi)
            out[key][a] = {
                "sim": float(np.sqrt(np.nansum(sim.mean_psd[sel_s, j]) * (sim.f_hz[1] - sim.f_hz[0]))),
                "real": float(np.sqrt(np.nansum(real[sel_r]) * (f_r[1] - f_r[0]))),
            }
    return out


def _own_hover_u(vehicle) -> float:
    """The class's own hover motor command under its motor law (default idle)."""
    v = get_vehicle(vehicle)
    return motor_law(v, 0.055).command_for_speed(v.hover_rotor_speed_rad_s)


def _repeatability(spec_a: dict, i: int, spec_b: dict, j: int) -> dict:
    """The log against itself: its first half's band i scored as if simulated against the second
    half's band j (the in-band fraction the data allows; 0.95 for equal spectra)."""
    from types import SimpleNamespace

    b = spec_a["bands"][i]
    ns = SimpleNamespace(
        f_hz=np.asarray(spec_a["f_hz"], float),
        n_windows=int(b["n_windows"]),
        mean_psd=np.column_stack([[np.nan if x is None else x for x in b["psd_rad2_s2_hz"][a]] for a in "xyz"]),
    )
    return fidelity(ns, spec_b, band=j)


def summary_table(out: dict) -> str:
    """Markdown: per band and axis, RMS above 40 Hz (log vs firmware in the loop), held out then in sample."""
    lines = [
        "| band | throttle | axis | log RMS > 40 Hz, °/s (held out) | sim RMS > 40 Hz, °/s | in-band fraction (held out) "
        "| in-band fraction (in sample) | log half vs half |",
        "|---|---|---|---|---|---|---|---|",
    ]
    deg = 180.0 / math.pi
    for r in out["bands"]:
        for a in "xyz":
            h = (r["held_out"] or {}).get(a)
            s = r["in_sample"][a]
            rep = (r.get("log_first_vs_second_half") or {}).get(a)
            lines.append(
                f"| {r['band']} | {r['throttle'][0]:.2f}–{r['throttle'][1]:.2f} | {a} | "
                f"{(h['rms_real_rad_s'] * deg) if h else float('nan'):.2f} | {s['rms_sim_rad_s'] * deg:.2f} | "
                f"{h['in_band_fraction'] if h else float('nan'):.2f} | {s['in_band_fraction']:.2f} | "
                f"{rep['in_band_fraction'] if rep else float('nan'):.2f} |"
            )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flight", required=True)
    ap.add_argument("--vehicle", default="racing5")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--duration-s", type=float, default=6.0)
    ap.add_argument("--bands", default=None, help="comma-separated band indices (default all)")
    ap.add_argument(
        "--at-band-throttle",
        action="store_true",
        help="fly each band at its own motor command (payload), the band wholly shaped",
    )
    ap.add_argument(
        "--inject-to-nyquist",
        action="store_true",
        help="inject the band's PSD up to the logged Nyquist (past the spec's reliable limit)",
    )
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    bands = None if a.bands is None else {int(x) for x in a.bands.split(",")}
    out = run(
        flight=a.flight,
        vehicle=a.vehicle,
        seed=a.seed,
        duration_s=a.duration_s,
        bands=bands,
        at_band_throttle=a.at_band_throttle,
        inject_to_nyquist=a.inject_to_nyquist,
    )
    if a.json:
        print(json.dumps(out, indent=1, default=str))
    else:
        print(
            f"{out['flight']} on {out['vehicle']}, {out['firmware']}; {len(out['settings_applied'])} settings from the "
            f"header, {len(out['settings_skipped'])} skipped"
        )
        print(summary_table(out))


if __name__ == "__main__":
    main()
