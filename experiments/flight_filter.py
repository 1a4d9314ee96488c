"""Closed-loop check of ``gyroharness filter``: the candidate chains flown by the simulator with
the pilot's identified vibration, scored on what the filter changes.

The vehicle is a registered class (default ``racing25``: the 2.5-inch quad that flew the shared
log). The flight's vibration spec (its middle throttle band by default) enters as everywhere
else (:func:`sim.spec_vibration.spec_injection`): the rotor line through the rotors' static and
hub-moment unbalance at the rotor speed the controller commands, the rest of the band as the
registry effect ``vibration``'s shaped part in the gyro (so the rate loop flies on it). A chain
is the firmware chain of ``gyroharness filter`` (re-rated to the simulator's 1-kHz gyro; stages
at or above its Nyquist dropped) after the power-up bias removal; RPM-filter candidates fly
:class:`gyrocore.flight.filters.RpmNotch` fed the simulated rotor speeds.

What the filter changes, each isolated by a paired flight (same seed: same gyro noise, rotor
phases, shaped-vibration draw):

* ``att_vibration_deg`` — steady hover (no manoeuvres) with the vibration against the same hover
  without it (same chain): RMS of the angle between the two attitudes. What the vibration the
  chain lets through does to the attitude.
* ``att_delay_deg`` — attitude steps without vibration: the RMS tracking error's increase over
  the unfiltered chain's, in quadrature, √max(RMS_c² − RMS_none², 0). What the chain's delay costs.
* ``att_delay_flight_deg`` — the chain's extra gyro delay (measured in the step flight, over the
  unfiltered chain's) times the pilot's own flight-band rate (RMS of the log's gyro below 30 Hz):
  a pure delay τ on a rate ω lags the attitude by τ·ω. The simulated airframe's step tracking
  cannot stand in for the pilot's acro flight (its rate loop is set by the estimated motor lag),
  so the delay is priced at the flight's own rates.
* ``attitude_cost_deg`` = hypot of the three; ``motor_noise_n`` (motor thrust commands above
  20 Hz in the vibrating hover); ``delay_ms`` (gyro delay measured in the step flight).

Recommendation (as ``gyroharness filter``): least attitude cost among the chains whose motor noise
does not exceed the as-flown chain's, per seed; the recommendation is stable when every seed
picks the same chain.

    python -m experiments.flight_filter --flight FLIGHT.BBL [--vehicle racing25] [--seeds 3] [--duration-s 8]
    gyroharness filter-closed-loop FLIGHT.BBL [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
import warnings

import numpy as np

from gyrocore.data.recording import read_csv
from gyrocore.flight import preview as P
from gyrocore.flight.preview import recommend_filter
from gyrocore.flight.vibration import read_spec, write_spec
from gyrocore.readers.convert import detect_format, load_any
from sim.quadrotor import quat_angle_rad
from sim.spec_vibration import spec_injection

GYRO_RATE_HZ = 1000.0
SETTLE_S = 1.0


def _rerated(stages, rate_hz):
    out = []
    for s in stages:
        if s.get("dynamic") or s["kind"] == "fir" or float(s["cutoff_hz"]) >= rate_hz / 2:
            continue
        out.append(dict(s, rate_hz=rate_hz))
    return out


def fly(
    stages,
    *,
    duration_s: float,
    seed: int,
    vehicle: str = "racing25",
    preset: str = "icm42688p",
    vibration=True,
    shaped: dict | None = None,
    rpm: bool = False,
    manoeuvres: bool = True,
):
    """One closed-loop flight of a chain; returns (FlightLog, chain stage names).

    ``vibration``: the rotor physics (True = the class's default, False = none, or a
    VibrationSpec); ``shaped``: the registry effect ``vibration``'s shaped part (overrides of the
    synthetic gyro, :func:`sim.spec_vibration.spec_injection`) or None.
    """
    from gyrocore.flight.filters import AffineCorrection, Pipeline, RpmNotch, chain_filters
    from sim.controller import small_steps
    from sim.gyro import SyntheticGyro
    from sim.quadrotor import fly_hover

    n = int(math.floor(duration_s * GYRO_RATE_HZ + 1e-9))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        g = SyntheticGyro(preset, rate_hz=GYRO_RATE_HZ, seed=seed, overrides=shaped or None)
    flts = chain_filters(_rerated(stages, GYRO_RATE_HZ))
    if rpm:
        flts = [RpmNotch(GYRO_RATE_HZ), *flts]
    pipe = Pipeline([AffineCorrection(g.power_up_bias(0)), *flts])
    _, log = fly_hover(
        duration_s=duration_s,
        gyro=g.stream(n),
        pipeline=pipe,
        manoeuvres=small_steps(duration_s) if manoeuvres else (),
        vibration=vibration,
        seed=seed,
        gyro_rate_hz=GYRO_RATE_HZ,
        vehicle=vehicle,
    )
    return log, [f.name for f in flts]


def _angle_between_deg(qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
    return np.degrees(quat_angle_rad(qa, qb))


def score_chain(
    stages,
    *,
    hover_vib,
    shaped,
    seed: int,
    duration_s: float,
    vehicle: str,
    rpm: bool = False,
    track_none_deg: float | None = None,
    delay_none_ms: float | None = None,
    flight_rate_rms_rad_s: float = 0.0,
) -> dict:
    """The paired flights of one chain (module docstring) -> scores."""
    keep_s = SETTLE_S
    log_v, chain = fly(
        stages,
        duration_s=duration_s,
        seed=seed,
        vehicle=vehicle,
        vibration=hover_vib or True,
        shaped=shaped,
        rpm=rpm,
        manoeuvres=False,
    )
    log_r, _ = fly(
        stages,
        duration_s=duration_s,
        seed=seed,
        vehicle=vehicle,
        vibration=False,
        shaped=None,
        rpm=rpm,
        manoeuvres=False,
    )
    log_m, _ = fly(
        stages,
        duration_s=duration_s,
        seed=seed,
        vehicle=vehicle,
        vibration=False,
        shaped=None,
        rpm=rpm,
        manoeuvres=True,
    )
    k = log_v.t_s >= keep_s
    ok = all(
        np.all(np.isfinite(lg.q_WB_wxyz)) and float(np.max(lg.tilt_rad())) < math.radians(60)
        for lg in (log_v, log_r, log_m)
    )
    nan = float("nan")
    if not ok:
        return {
            "crashed": True,
            "chain": chain,
            "att_vibration_deg": nan,
            "att_delay_deg": nan,
            "att_delay_flight_deg": nan,
            "attitude_cost_deg": nan,
            "motor_noise_n": nan,
            "delay_ms": nan,
            "track_rms_deg": nan,
        }
    att_vib = float(np.sqrt(np.mean(_angle_between_deg(log_v.q_WB_wxyz[k], log_r.q_WB_wxyz[k]) ** 2)))
    track = float(np.degrees(np.sqrt(np.mean(log_m.attitude_error_rad()[k] ** 2))))
    base = track if track_none_deg is None else track_none_deg
    att_delay = math.sqrt(max(track * track - base * base, 0.0))
    delay_ms = 1e3 * log_m.gyro_delay_s()
    extra_s = max(delay_ms - (delay_ms if delay_none_ms is None else delay_none_ms), 0.0) / 1e3
    att_flight = math.degrees(extra_s * float(flight_rate_rms_rad_s))
    return {
        "crashed": False,
        "chain": chain,
        "att_vibration_deg": att_vib,
        "att_delay_deg": att_delay,
        "att_delay_flight_deg": att_flight,
        "attitude_cost_deg": math.sqrt(att_vib**2 + att_delay**2 + att_flight**2),
        "motor_noise_n": log_v.motor_noise_n(t_from_s=keep_s),
        "delay_ms": delay_ms,
        "track_rms_deg": track,
    }


def _candidates(fj: dict, *, physics: bool, extra_pt1=(60.0, 150.0, 250.0)) -> dict:
    """name -> (stages, rpm, open-loop row key) from ``gyroharness filter``'s result."""
    rate = float(fj.get("filter_rate_hz", 8000.0))
    cands = {"none": ([], False)}
    for key in ("as_flown", "recommended", "article", "px4_ardupilot_lowpass"):
        if fj.get(key) and fj[key].get("stages") is not None:
            cands[key] = (list(fj[key]["stages"]), False)
    for k, v in (fj.get("defaults") or {}).items():
        if v.get("stages") is not None:
            cands[k] = (list(v["stages"]), False)
    for fc in extra_pt1:
        cands[f"pt1 {fc:g} Hz"] = ([P._stage("pt1", fc, rate)], False)
    if physics:
        # the RPM filter tracks the simulator's rotors (the rotor line is in the physics)
        if fj.get("with_rpm_filter") and fj["with_rpm_filter"].get("stages") is not None:
            cands["with_rpm_filter"] = (list(fj["with_rpm_filter"]["stages"]), True)
        if "as_flown" in cands:
            cands["as_flown + rpm"] = (cands["as_flown"][0], True)
    return cands


def _pick(rows: dict) -> tuple[str, float]:
    """Least attitude cost with motor noise <= the as-flown chain's (else <= the least noisy's)."""
    ok = {k: r for k, r in rows.items() if not r["crashed"]}
    budget = ok["as_flown"]["motor_noise_n"] if "as_flown" in ok else min(r["motor_noise_n"] for r in ok.values())
    pool = {k: r for k, r in ok.items() if r["motor_noise_n"] <= budget * (1 + 1e-9)}
    best = min(pool, key=lambda k: (pool[k]["attitude_cost_deg"], pool[k]["motor_noise_n"]))
    return best, budget


def run(
    *,
    flight: str,
    vehicle: str = "racing25",
    seeds=(0, 1, 2),
    duration_s: float = 8.0,
    band="middle",
    physics: bool = True,
    n_calib: int = 16,
    calib_s: float = 2.0,
    candidates: dict | None = None,
) -> dict:
    """The closed-loop recommendation for a flight log (module docstring). Returns the JSON dict
    (DESIGN.md keys ``recommended``, ``as_flown``, ``firmware``, ``defaults``; plus per-seed picks,
    ``stable`` and every chain's scores per seed)."""
    rec = read_csv(flight) if detect_format(flight) == "csv" else load_any(flight)
    fj = recommend_filter(rec)
    hv, shaped, info = _flight_vibration(
        fj, flight, band=band, vehicle=vehicle, physics=physics, n_calib=n_calib, calib_s=calib_s
    )
    cands = candidates or _candidates(fj, physics=physics)
    w_rms = float(fj["flight_rate_rms_rad_s"])
    per_seed = [
        _score_seed(int(s), cands, hover_vib=hv, shaped=shaped, duration_s=duration_s, vehicle=vehicle, w_rms=w_rms)
        for s in seeds
    ]
    picks = [ps["pick"] for ps in per_seed]
    summary = _chain_summary(per_seed)
    mode = max(set(picks), key=picks.count)
    by_open = {
        "as_flown": fj.get("as_flown"),
        "recommended": fj.get("recommended"),
        "article": fj.get("article"),
        "px4_ardupilot_lowpass": fj.get("px4_ardupilot_lowpass"),
        "with_rpm_filter": fj.get("with_rpm_filter"),
        **(fj.get("defaults") or {}),
    }

    def public(name):
        return _public(name, cands, summary)

    rec_pub = public(mode)
    b2 = {
        k: summary[k]["attitude_cost_deg"]["mean"]
        for k in ("px4_default", "ardupilot_default", "px4_ardupilot_lowpass")
        if k in summary
    }
    b2best = min(b2, key=b2.get) if b2 else None
    b2fc = public(b2best)["cutoff_hz"] if b2best else None
    return {
        "flight": flight,
        "vehicle": vehicle,
        "flight_rate_rms_rad_s": float(fj["flight_rate_rms_rad_s"]),
        "band": band,
        "duration_s": duration_s,
        "seeds": [int(s) for s in seeds],
        "recommended": rec_pub,
        "as_flown": public("as_flown") if "as_flown" in summary else None,
        "defaults": {k: public(k) for k in ("betaflight_default", "px4_default", "ardupilot_default") if k in summary},
        "open_loop_recommended": public("recommended") if "recommended" in summary else None,
        "firmware": {
            "betaflight": _betaflight_lines(rec.meta, rec_pub, cands[mode]),
            "px4": {"IMU_GYRO_CUTOFF": round(b2fc)} if b2fc else {},
            "ardupilot": {"INS_GYRO_FILTER": round(b2fc)} if b2fc else {},
        },
        "picks_per_seed": picks,
        "stable": len(set(picks)) == 1,
        "chains": summary,
        "per_seed": per_seed,
        "injection": info,
        "open_loop": {k: (v["name"] if v else None) for k, v in by_open.items()},
        "scores": {
            "att_vibration_deg": "RMS angle between the vibrating and the vibration-free steady hover (same chain, seed)",
            "att_delay_deg": "sqrt(max(RMS_track^2 - RMS_track(none)^2, 0)) on attitude steps without vibration",
            "att_delay_flight_deg": "(delay - delay(none)) x the log's flight-band rate RMS",
            "attitude_cost": "sqrt(att_vibration^2 + att_delay^2 + att_delay_flight^2), deg",
            "motor_noise": "RMS of the motor thrust commands above 20 Hz in the vibrating hover, N",
        },
        "notes": [
            f"chains re-rated to the simulator's {GYRO_RATE_HZ:g}-Hz gyro (stages at or above its Nyquist dropped)",
            f"vehicle {vehicle}: motor time constant {1e3 * _tau(vehicle):.0f} ms (estimate); the delay cost depends on it",
        ],
    }


def _flight_vibration(fj: dict, flight: str, *, band, vehicle: str, physics: bool, n_calib: int, calib_s: float):
    """The flight's vibration spec (from the filter recommendation's analysis) as the simulator's
    injection: (hover vibration, shaped part, info) of :func:`sim.spec_vibration.spec_injection`."""
    with tempfile.TemporaryDirectory() as d:
        p = os.path.join(d, "spec.json")
        write_spec(fj["_res"], p, source=flight)
        spec = read_spec(p)
    return spec_injection(spec, band=band, vehicle=vehicle, physics=physics, seed=0, n_calib=n_calib, calib_s=calib_s)


def _score_seed(seed: int, cands: dict, *, hover_vib, shaped, duration_s: float, vehicle: str, w_rms: float) -> dict:
    """Every candidate chain flown on one seed (:func:`score_chain`, the unfiltered gyro first) and that seed's pick."""
    none = score_chain([], hover_vib=hover_vib, shaped=shaped, seed=seed, duration_s=duration_s, vehicle=vehicle)
    rows = {"none": none}
    for name, (st, rpm) in cands.items():
        if name == "none":
            continue
        rows[name] = score_chain(
            st,
            hover_vib=hover_vib,
            shaped=shaped,
            seed=seed,
            duration_s=duration_s,
            vehicle=vehicle,
            rpm=rpm,
            track_none_deg=none["track_rms_deg"],
            delay_none_ms=none["delay_ms"],
            flight_rate_rms_rad_s=w_rms,
        )
    best, budget = _pick(rows)
    return {"seed": seed, "pick": best, "budget_motor_noise_n": budget, "rows": rows}


def _chain_summary(per_seed: list[dict]) -> dict:
    """Per chain: mean and SD over the seeds of each score, and the chain flown."""
    summary = {}
    for name in per_seed[0]["rows"]:
        vals = {
            k: [ps["rows"][name][k] for ps in per_seed]
            for k in (
                "attitude_cost_deg",
                "att_vibration_deg",
                "att_delay_deg",
                "att_delay_flight_deg",
                "motor_noise_n",
                "delay_ms",
            )
        }
        summary[name] = {
            k: {"mean": float(np.mean(v)), "sd": float(np.std(v, ddof=1)) if len(v) > 1 else float("nan")}
            for k, v in vals.items()
        }
        summary[name]["chain"] = per_seed[0]["rows"][name]["chain"]
    return summary


def _public(name: str, cands: dict, summary: dict) -> dict:
    """A chain in the filter JSON's public form (its low-pass, notches, mean scores)."""
    st, rpm = cands.get(name, ([], False))
    lp = [x for x in st if x["kind"] in ("pt1", "pt2", "pt3", "biquad", "butter2", "article")]
    m = summary[name]
    return {
        "filter": lp[0]["kind"] if lp else "none",
        "cutoff_hz": float(lp[0]["cutoff_hz"]) if lp else None,
        "notches_hz": [float(x["cutoff_hz"]) for x in st if x["kind"] == "notch"],
        "attitude_cost": m["attitude_cost_deg"]["mean"],
        "delay_ms": m["delay_ms"]["mean"],
        "motor_noise": m["motor_noise_n"]["mean"],
        "rpm_filter": bool(rpm),
        "name": name,
        "chain_flown": m["chain"],
        "units": {"attitude_cost": "deg", "delay_ms": "ms", "motor_noise": "N"},
    }


def _betaflight_lines(meta: dict, rec_pub: dict, cand: tuple) -> list[str]:
    """The Betaflight ``set`` lines of the recommended chain (a comment for another firmware)."""
    if meta.get("firmware_name", "betaflight") != "betaflight":
        return [f"# {meta.get('firmware_name')} log: Betaflight CLI names do not apply"]
    version = tuple(int(x) for x in meta["firmware_version"].split(".")) if "firmware_version" in meta else None
    st, rpm = cand
    if rec_pub["filter"] in ("pt1", "pt2", "pt3", "biquad"):
        bf = P.betaflight_cli({"filter": rec_pub["filter"], "cutoff_hz": rec_pub["cutoff_hz"], "stages": st}, version)
    elif rec_pub["filter"] == "none":
        bf = ["# no static gyro low-pass recommended"]
    else:
        bf = [f"# {rec_pub['filter']} is not a Betaflight gyro filter: see the px4/ardupilot names"]
    if rpm:
        v = version or (4, 5, 0)
        bf += (
            ["# the RPM filter needs Betaflight 4.0+ with bidirectional DShot (eRPM telemetry)"]
            if v < (4, 0, 0)
            else ["set dshot_bidir = ON"]
            + (["set gyro_rpm_notch_harmonics = 3"] if v < (4, 3, 0) else ["set rpm_filter_harmonics = 3"])
        )
    return bf


def _tau(vehicle):
    from sim.vehicles import get_vehicle

    return get_vehicle(vehicle).motor_tau_s


def print_table(out: dict) -> None:
    print(
        "| chain | flown as | attitude cost, deg | vibration part | step-tracking delay part | flight-rate delay part | "
        "motor noise, N | gyro delay, ms |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for k, m in out["chains"].items():

        def f(key, fmt):
            v = m[key]
            return (fmt % v["mean"]) + (f" ± {fmt % v['sd']}" if np.isfinite(v["sd"]) else "")

        print(
            f"| {k} | {' -> '.join(m['chain']) or 'none'} | {f('attitude_cost_deg', '%.4f')} | {f('att_vibration_deg', '%.4f')} | "
            f"{f('att_delay_deg', '%.4f')} | {f('att_delay_flight_deg', '%.4f')} | {f('motor_noise_n', '%.4f')} | "
            f"{f('delay_ms', '%.2f')} |"
        )
    print(f"picks per seed {out['seeds']}: {out['picks_per_seed']} (stable: {out['stable']})")
    print(
        "recommended:",
        out["recommended"]["name"],
        "| betaflight:",
        "; ".join(out["firmware"]["betaflight"]),
        "| px4:",
        out["firmware"]["px4"],
        "| ardupilot:",
        out["firmware"]["ardupilot"],
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flight", required=True)
    ap.add_argument("--vehicle", default="racing25")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--duration-s", type=float, default=8.0)
    ap.add_argument("--band", default="middle")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    out = run(flight=a.flight, vehicle=a.vehicle, seeds=tuple(range(a.seeds)), duration_s=a.duration_s, band=a.band)
    if a.json:
        print(json.dumps({k: v for k, v in out.items() if k != "per_seed"}, indent=1, default=str))
    else:
        print_table(out)


if __name__ == "__main__":
    main()
