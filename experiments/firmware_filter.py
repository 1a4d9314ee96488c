"""``gyroharness filter-closed-loop FLIGHT --firmware betaflight``: the gyro filter chain chosen by
flying the candidates with the firmware in the loop (the project's-controller
version is :mod:`experiments.flight_filter`).

The firmware is booted with the pilot's whole tune, read from the log's header through the bridge
(PIDs, rates, every filter: static and dynamic gyro low-passes, notches, the dynamic notch, the
RPM filter, the D-term chain); the vehicle class flies with the flight's vibration (its spec's band
through :func:`sim.spec_vibration.spec_injection`: rotor line through the rotors' unbalance, the
rest as the gyro's shaped vibration). A candidate is the tune plus a few ``set`` lines:

* ``as_flown`` — the tune unchanged, dynamic filters included;
* ``pt1 F Hz`` — the gyro low-pass replaced by one static PT1 at F (60, 150, 250 Hz), notches and
  RPM filter as flown;
* ``no_gyro_lowpass`` — no gyro low-pass (notches, dynamic notch and RPM filter as flown);
* ``no_dyn_notch`` / ``no_rpm_filter`` — the tune without its dynamic notch / RPM filter;
* ``none`` — every gyro filter off (the delay baseline).

Scores per candidate and seed (paired: same seed = same gyro, rotor phases, shaped draw), from two
``steps`` flights (steady hover, then rate pulses) — A with the vibration, B without:

* ``att_vibration_deg`` — RMS angle between A's and B's attitude over the steady hover: what the
  vibration the chain lets through does to the attitude;
* ``att_delay_deg`` — √max(RMS_track(B)² − RMS_track(B, none)², 0): what the chain's delay costs
  the tracking of the rate pulses;
* ``att_delay_flight_deg`` — the chain's extra gyro delay over ``none`` (measured in A) times the
  pilot's own flight-band rate (RMS of the log's gyro below 30 Hz, airborne), as
  :mod:`experiments.flight_filter` prices it: a delay τ on a rate ω lags the attitude by τ·ω;
* ``attitude_cost_deg`` = hypot of the three; ``motor_noise_pct`` (A's motor outputs above 20 Hz over
  the hover, % of full output); ``dterm_noise`` (A's D term above 20 Hz, firmware units); the
  measured gyro delay, rise and overshoot of the rate steps.

Pick (per seed, as :mod:`experiments.flight_filter`): least attitude cost among the candidates whose
motor noise is at most the as-flown tune's; the recommendation is the seeds' most frequent pick,
given as the ``set`` lines it changes in the tune (none when it is the tune itself).
"""

from __future__ import annotations

import math

import numpy as np

from sim.quadrotor import quat_angle_rad
from gyrocore.errors import GyroInputError
from experiments.firmware_fly import fly, settings_lines_from
from experiments.montecarlo import execute, MonteCarloTask, TaskResult
from gyrocore.data.recording import read_csv
from gyrocore.flight.vibration import analyse, read_spec, write_spec
from gyrocore.readers.convert import detect_format, load_any
from sim.firmware.build import ensure_binary, FirmwareBinary
from sim.fw_flight import FwFlightOptions
from sim.spec_vibration import spec_injection
from sim.vehicles import get_vehicle

__all__ = ["candidates", "changed_lines", "print_table", "run"]

SETTLE_S = 1.0
#: every gyro filter off (Betaflight 4.3+ names)
_OFF_LPF = ("set gyro_lpf1_static_hz = 0", "set gyro_lpf1_dyn_min_hz = 0", "set gyro_lpf2_static_hz = 0")


def candidates(*, extra_pt1=(60.0, 150.0, 250.0)) -> dict[str, list[str]]:
    """name -> the ``set`` lines a candidate adds to the tune (module docstring)."""
    c: dict[str, list[str]] = {"as_flown": []}
    for fc in extra_pt1:
        c[f"pt1 {fc:g} Hz"] = [
            "set gyro_lpf1_type = PT1",
            f"set gyro_lpf1_static_hz = {fc:.0f}",
            "set gyro_lpf1_dyn_min_hz = 0",
            "set gyro_lpf2_static_hz = 0",
        ]
    c["no_gyro_lowpass"] = list(_OFF_LPF)
    c["no_dyn_notch"] = ["set dyn_notch_count = 0"]
    c["no_rpm_filter"] = ["set rpm_filter_harmonics = 0"]
    c["none"] = list(_OFF_LPF) + [
        "set dyn_notch_count = 0",
        "set rpm_filter_harmonics = 0",
        "set gyro_notch1_hz = 0",
        "set gyro_notch2_hz = 0",
    ]
    return c


def _kv(line: str) -> tuple[str, str]:
    s = line.strip()
    s = s[4:] if s.lower().startswith("set ") else s
    k, _, v = s.partition("=")
    return k.strip().lower(), v.strip().upper()


def changed_lines(tune: list[str], lines: list[str]) -> list[str]:
    """The candidate's lines whose value differs from the tune's (a name the tune does not set is kept)."""
    have = dict(_kv(x) for x in tune if "=" in x and not x.strip().lower().startswith(("aux", "feature")))
    return [x for x in lines if have.get(_kv(x)[0]) != _kv(x)[1]]


def _angle_rms_deg(qa, qb, mask) -> float:
    return float(np.degrees(np.sqrt(np.mean(quat_angle_rad(qa[mask], qb[mask]) ** 2))))


def fw_filter_task(task):
    """Monte Carlo task (:mod:`experiments.montecarlo`): every candidate of one seed; metrics
    ``"<candidate>|<metric>"``."""
    o = dict(task.options)
    tune, cands = list(o["tune"]), dict(o["candidates"])
    hv, over = o["hover_vibration"], dict(o["overrides"])
    base = dict(
        scenario="steps",
        vehicle=o["vehicle"],
        duration_s=float(task.duration_s),
        seed=int(task.seed),
        sensor=task.sensor,
        settle_s=SETTLE_S,
    )
    rows = {}
    for name, lines in cands.items():
        a, _ = fly(
            FwFlightOptions(**base, vibration=hv, gyro_overrides=over), list(lines), lenient=tune, binary=o["binary"]
        )
        b, _ = fly(
            FwFlightOptions(**base, vibration=False, gyro_overrides=None), list(lines), lenient=tune, binary=o["binary"]
        )
        sa, sb = a.scores(SETTLE_S), b.scores(SETTLE_S)
        nan = float("nan")
        if sa["crashed"] or sb["crashed"]:
            rows[name] = {"crashed": 1.0}
            continue
        hov = a.hover_mask(SETTLE_S)
        rows[name] = {
            "crashed": 0.0,
            "att_vibration_deg": _angle_rms_deg(a.q_WB_wxyz, b.q_WB_wxyz, hov),
            "track_rms_deg": sb["step_track_rms_deg"],
            "motor_noise_pct": 100.0 * sa["motor_noise_above_20hz"],
            "dterm_noise": sa["dterm_noise_above_20hz"] if sa["dterm_noise_above_20hz"] is not None else nan,
            "hover_att_rms_deg": sa["hover_att_rms_deg"],
            "delay_ms": sa["gyro_delay_ms"],
            "rise_ms": sa["step_rise_ms"],
            "overshoot_pct": sa["step_overshoot_pct"],
        }
    t_none = rows.get("none", {}).get("track_rms_deg", float("nan"))
    d_none = rows.get("none", {}).get("delay_ms", float("nan"))
    w_rms = float(o["flight_rate_rms_rad_s"])
    metrics = {}
    for name, r in rows.items():
        if r.get("crashed"):
            metrics[f"{name}|crashed"] = 1.0
            continue
        base_t = t_none if np.isfinite(t_none) else r["track_rms_deg"]
        r["att_delay_deg"] = math.sqrt(max(r["track_rms_deg"] ** 2 - base_t**2, 0.0))
        extra_s = max(r["delay_ms"] - d_none, 0.0) / 1e3 if np.isfinite(d_none) else 0.0
        r["att_delay_flight_deg"] = math.degrees(extra_s * w_rms)
        r["attitude_cost_deg"] = math.sqrt(
            r["att_vibration_deg"] ** 2 + r["att_delay_deg"] ** 2 + r["att_delay_flight_deg"] ** 2
        )
        for k, v in r.items():
            metrics[f"{name}|{k}"] = float(v)
    return TaskResult.from_task(task, metrics)


def _pick(rows: dict) -> tuple[str, float]:
    """Least attitude cost among the candidates with motor noise <= the as-flown tune's."""
    ok = {k: r for k, r in rows.items() if not r.get("crashed") and np.isfinite(r.get("attitude_cost_deg", np.nan))}
    if not ok:
        raise GyroInputError("every candidate crashed in the simulator")
    budget = ok["as_flown"]["motor_noise_pct"] if "as_flown" in ok else min(r["motor_noise_pct"] for r in ok.values())
    pool = {k: r for k, r in ok.items() if r["motor_noise_pct"] <= budget * (1 + 1e-9)}
    return min(pool, key=lambda k: (pool[k]["attitude_cost_deg"], pool[k]["motor_noise_pct"])), budget


def run(
    *,
    flight: str,
    vehicle: str = "racing25",
    seeds=(0, 1),
    duration_s: float = 4.0,
    band="middle",
    sensor: str = "icm42688p",
    n_calib: int = 16,
    calib_s: float = 2.0,
    workers: int = 1,
    scheduler: str | None = None,
    binary=None,
    cands: dict | None = None,
) -> dict:
    """Fly every candidate with the firmware and recommend one (module docstring). Returns the JSON dict:
    ``recommended`` (name, ``set`` lines changed, scores), ``as_flown``, ``chains`` (mean and SD over the
    seeds), ``picks_per_seed``, ``stable``, ``firmware``, ``tune`` (the lines applied)."""
    import os
    import tempfile

    get_vehicle(vehicle)
    rec = read_csv(flight) if detect_format(flight) == "csv" else load_any(flight)
    if rec.meta.get("firmware_name", "betaflight") != "betaflight":
        raise GyroInputError(
            f"{flight}: a {rec.meta.get('firmware_name')} log; --firmware betaflight flies a Betaflight tune"
        )
    # the flight's vibration spec, as `gyroharness vibration FLIGHT -o SPEC` (before the firmware's filters)
    res = analyse(rec, undo=True)
    tune = settings_lines_from(flight)
    with tempfile.TemporaryDirectory() as d:
        p = os.path.join(d, "spec.json")
        write_spec(res, p, source=flight)
        spec = read_spec(p)
    hv, over, info = spec_injection(
        spec, band=band, vehicle=vehicle, physics=True, seed=0, n_calib=n_calib, calib_s=calib_s
    )
    cands = cands or candidates()
    # the pilot's flight-band rate (the attitude cost of delay): RMS of the log's gyro below 30 Hz, airborne
    from scipy import signal

    sos = signal.butter(4, 30.0, fs=res.rate_hz, output="sos")
    g_lp = signal.sosfiltfilt(sos, rec.gyro_rad_s, axis=0)
    air = rec.extra["motor_cmd_mean"] >= 0.1 if "motor_cmd_mean" in rec.extra else np.ones(rec.n, bool)
    w_rms = float(np.sqrt(np.mean(np.sum(g_lp[air] ** 2, axis=1))))
    fb = binary if isinstance(binary, FirmwareBinary) else ensure_binary()
    label = f"{fb.firmware} {fb.version}"
    opts = (
        ("tune", tuple(tune)),
        ("candidates", tuple((k, tuple(v)) for k, v in cands.items())),
        ("hover_vibration", hv),
        ("overrides", tuple(over.items())),
        ("vehicle", vehicle),
        ("binary", fb),
        ("flight_rate_rms_rad_s", w_rms),
    )
    tasks = [
        MonteCarloTask(
            index=i,
            scenario="filter-closed-loop-firmware",
            sensor=sensor,
            instance=i,
            seed=int(s),
            duration_s=float(duration_s),
            options=opts,
        )
        for i, s in enumerate(seeds)
    ]
    results, backend, nw = execute(fw_filter_task, tasks, workers=workers, scheduler=scheduler)
    per_seed, picks = [], []
    for r in results:
        m = r.metrics_dict
        rows = {}
        for name in cands:
            if m.get(f"{name}|crashed", 0.0):
                rows[name] = {"crashed": True}
            else:
                rows[name] = {k.split("|", 1)[1]: v for k, v in m.items() if k.startswith(name + "|")}
                rows[name]["crashed"] = False
        best, budget = _pick(rows)
        picks.append(best)
        per_seed.append({"seed": r.seed, "pick": best, "budget_motor_noise_pct": budget, "rows": rows})
    keys = (
        "attitude_cost_deg",
        "att_vibration_deg",
        "att_delay_deg",
        "att_delay_flight_deg",
        "motor_noise_pct",
        "dterm_noise",
        "delay_ms",
        "rise_ms",
        "overshoot_pct",
        "hover_att_rms_deg",
    )
    chains = {}
    for name in cands:
        vals = {
            k: [ps["rows"][name].get(k, np.nan) for ps in per_seed if not ps["rows"][name]["crashed"]] for k in keys
        }
        chains[name] = {
            k: {
                "mean": float(np.mean(v)) if v else float("nan"),
                "sd": float(np.std(v, ddof=1)) if len(v) > 1 else float("nan"),
            }
            for k, v in vals.items()
        }
        chains[name]["lines"] = list(cands[name])
        chains[name]["crashed_seeds"] = sum(ps["rows"][name]["crashed"] for ps in per_seed)
    mode = max(set(picks), key=picks.count)

    def public(name):
        c = chains[name]
        return {
            "name": name,
            "set": changed_lines(tune, cands[name]),
            "attitude_cost": c["attitude_cost_deg"]["mean"],
            "motor_noise": c["motor_noise_pct"]["mean"],
            "delay_ms": c["delay_ms"]["mean"],
            "units": {"attitude_cost": "deg", "motor_noise": "% of full motor output above 20 Hz", "delay_ms": "ms"},
        }

    rec_pub = public(mode)
    return {
        "flight": flight,
        "vehicle": vehicle,
        "firmware": label,
        "band": band,
        "duration_s": duration_s,
        "flight_rate_rms_rad_s": w_rms,
        "seeds": [int(s) for s in seeds],
        "backend": backend,
        "workers": nw,
        "recommended": rec_pub,
        "as_flown": public("as_flown"),
        "firmware_lines": {"betaflight": rec_pub["set"] or ["# keep the tune as flown"]},
        "picks_per_seed": picks,
        "stable": len(set(picks)) == 1,
        "chains": chains,
        "tune": tune,
        "injection": info,
        "scores": {
            "att_vibration_deg": "RMS angle between the vibrating and the vibration-free flight over the steady hover",
            "att_delay_deg": "sqrt(max(RMS_track^2 - RMS_track(none)^2, 0)) over the rate pulses, no vibration",
            "att_delay_flight_deg": "(delay - delay(none)) x the log's flight-band rate RMS",
            "attitude_cost": "sqrt(att_vibration^2 + att_delay^2 + att_delay_flight^2), deg",
            "motor_noise": "RMS of the motor outputs above 20 Hz in the vibrating hover, % of full output",
        },
    }


def format_table(out: dict) -> str:
    """The flown candidates as a Markdown table with the recommendation (what ``print_table`` prints)."""
    rows = [
        f"Flown by {out['firmware']} on {out['vehicle']} with the log's tune ({len(out['tune'])} lines) and its "
        f"vibration (band {out['band']}); seeds {out['seeds']}",
        "",
        "| chain | set lines over the tune | attitude cost, deg | vibration part | step delay part | flight-rate delay "
        "part | motor noise, % | D-term noise | gyro delay, ms | rise, ms | overshoot, % |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for k, m in out["chains"].items():

        def f(key, fmt):
            v = m[key]
            return (fmt % v["mean"]) + (f" ± {fmt % v['sd']}" if np.isfinite(v["sd"]) else "")

        lines = "; ".join(x.replace("set ", "") for x in m["lines"]) or "(as flown)"
        rows.append(
            f"| {k} | {lines} | {f('attitude_cost_deg', '%.4f')} | {f('att_vibration_deg', '%.4f')} | "
            f"{f('att_delay_deg', '%.4f')} | {f('att_delay_flight_deg', '%.4f')} | {f('motor_noise_pct', '%.3f')} | "
            f"{f('dterm_noise', '%.2f')} | {f('delay_ms', '%.2f')} | {f('rise_ms', '%.1f')} | {f('overshoot_pct', '%.1f')} |"
        )
    rows.append("")
    rows.append(f"picks per seed {out['seeds']}: {out['picks_per_seed']} (stable: {out['stable']})")
    rows.append(
        "recommended: "
        + out["recommended"]["name"]
        + " | betaflight: "
        + "; ".join(out["firmware_lines"]["betaflight"])
    )
    return "\n".join(rows)


def print_table(out: dict) -> None:
    print(format_table(out))
