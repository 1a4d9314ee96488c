"""Closed-loop check of ``gyroharness filter``: the candidates flown by the simulator with the
measured vibration in the loop (issue 16 item 5).

A vehicle class (default ``racing5``, the 5-inch racing class: the class nearest the 2.5-inch
quad that flew the shared log; ``--vehicle f450`` for the first version's airframe) hovers with
small attitude steps. The spec band's rotor line enters through the rotor physics
(:func:`sim.spec_vibration.vibration_from_spec`: the imbalance that gives the measured line
power, at the rotor speed the controller commands); the rest of the band's PSD (without the real
line) is a shaped Gaussian disturbance added to the gyro sample by sample inside the loop
(:func:`gyrocore.vibration.synthesize`). The rate loop reads it through power-up-bias removal +
the chain under test (the firmware chains of ``gyroharness filter``, re-rated to the
simulator's gyro rate). Candidates with an RPM filter fly :class:`gyrocore.filters.RpmNotch`,
fed the simulator's rotor speeds every sample (as Betaflight's from eRPM). Scored as
``experiment cutoffs``: attitude tracking error (RMS, after 1 s), motor-command noise above
20 Hz, measured gyro delay.

    python -m experiments.flight_filter --spec spec.json --filter-json filter.json [--duration-s 20] [--seed 0]
        [--vehicle racing5|f450] [--no-physics]
"""

from __future__ import annotations

import argparse
import json
import math
import warnings

import numpy as np

GYRO_RATE_HZ = 1000.0
SETTLE_S = 1.0


class _Disturbed:
    """A gyro stream whose output carries a precomputed disturbance d[k] (rad/s)."""

    def __init__(self, inner, d: np.ndarray) -> None:
        self.inner, self.d = inner, d

    def step(self, k, t_s, omega_S, f_S, temp_c, *args, **kw):
        return self.inner.step(k, t_s, omega_S, f_S, temp_c, *args, **kw) + self.d[min(k, self.d.shape[0] - 1)]


def _rerated(stages, rate_hz):
    out = []
    for s in stages:
        if s.get("dynamic") or s["kind"] == "fir" or float(s["cutoff_hz"]) >= rate_hz / 2:
            continue
        out.append(dict(s, rate_hz=rate_hz))
    return out


def fly(stages, d, *, duration_s: float, seed: int, preset: str = "icm42688p", vehicle: str = "f450",
        vibration=True, rpm: bool = False) -> dict:
    from gyrocore.filters import AffineCorrection, Pipeline, RpmNotch, chain_filters
    from sim.controller import small_steps
    from sim.gyro import SyntheticGyro
    from sim.quadrotor import fly_hover

    n = int(math.floor(duration_s * GYRO_RATE_HZ + 1e-9))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        g = SyntheticGyro(preset, rate_hz=GYRO_RATE_HZ, seed=seed)
    flts = chain_filters(_rerated(stages, GYRO_RATE_HZ))
    if rpm:
        flts = [RpmNotch(GYRO_RATE_HZ), *flts]
    pipe = Pipeline([AffineCorrection(g.power_up_bias(0)), *flts])
    truth, log = fly_hover(duration_s=duration_s, gyro=_Disturbed(g.stream(n), d), pipeline=pipe,
                           manoeuvres=small_steps(duration_s), vibration=vibration, seed=seed, gyro_rate_hz=GYRO_RATE_HZ,
                           vehicle=vehicle)
    keep = log.t_s >= SETTLE_S
    ok = np.all(np.isfinite(log.q_WB_wxyz)) and float(np.max(log.tilt_rad())) < math.radians(60)
    nan = float("nan")
    return {"crashed": not ok,
            "att_rms_deg": float(np.degrees(np.sqrt(np.mean(log.attitude_error_rad()[keep] ** 2)))) if ok else nan,
            "motor_noise_n": log.motor_noise_n(t_from_s=SETTLE_S) if ok else nan,
            "delay_ms": 1e3 * log.gyro_delay_s() if ok else nan,
            "chain": [f.name for f in flts]}


def run(*, spec_path: str, filter_json: str, duration_s: float = 20.0, seed: int = 0, band="middle",
        vehicle: str = "racing5", physics: bool = True) -> dict:
    from gyrocore.vibration import read_spec, synthesize

    spec = read_spec(spec_path)
    fj = json.load(open(filter_json))
    n = int(duration_s * GYRO_RATE_HZ) + 1
    vib, exclude, info = True, (), None
    if physics:
        from sim.spec_vibration import vibration_from_spec

        vib, info = vibration_from_spec(spec, vehicle, band=band, seed=seed)
        f_line = info["real_line_hz"]
        half = max(3 * (float(spec["f_hz"][1]) - float(spec["f_hz"][0])), 0.06 * f_line)
        exclude = ((f_line - half, f_line + half),)
    d = synthesize(spec, n=n, rate_hz=GYRO_RATE_HZ, seed=int(np.random.SeedSequence([seed, 16]).generate_state(1)[0]), band=band,
                   exclude_hz=exclude)
    rows = fj.get("_rows_for_sim") or []
    cands = {"none": []}
    for key in ("recommended", "as_flown", "with_rpm_filter", "article", "px4_ardupilot_lowpass"):
        if fj.get(key) and fj[key].get("stages") is not None:
            cands[key] = fj[key]["stages"]
    for k, v in fj.get("defaults", {}).items():
        if v.get("stages") is not None:
            cands[k] = v["stages"]
    rpm_cands = {}
    if physics:
        # the RPM filter tracks the simulator's rotors; only where the spec's rotor line is in the physics
        if "with_rpm_filter" in cands:
            rpm_cands["with_rpm_filter"] = cands["with_rpm_filter"]
        if "as_flown" in cands:
            rpm_cands["as_flown+rpm"] = cands["as_flown"]
        rpm_cands["rpm_only"] = []
    caveat = (f"vehicle {vehicle}; the 2.5-inch quad's rotor line through the rotor imbalance at {vehicle}'s commanded rotor "
              "speed, the rest of its spectrum as an in-loop gyro disturbance (not motion)" if physics else
              f"vehicle {vehicle}; the 2.5-inch quad's vibration as an in-loop gyro disturbance (not motion); "
              "RPM notches not flown (the spec's lines are not tied to the vehicle's rotors)")
    out = {"spec": spec_path, "band": band, "duration_s": duration_s, "seed": seed, "vehicle": vehicle,
           "physics": info, "caveat": caveat, "rows": {}}
    for name, st in cands.items():
        out["rows"][name] = fly(st, d, duration_s=duration_s, seed=seed, vehicle=vehicle, vibration=vib)
    for name, st in rpm_cands.items():
        key = name if name != "with_rpm_filter" else "with_rpm_filter (+ RPM notch)"
        out["rows"][key] = fly(st, d, duration_s=duration_s, seed=seed, vehicle=vehicle, vibration=vib, rpm=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", required=True)
    ap.add_argument("--filter-json", required=True)
    ap.add_argument("--duration-s", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--vehicle", default="racing5")
    ap.add_argument("--no-physics", action="store_true", help="the whole spec band as in-loop disturbance (first version)")
    a = ap.parse_args()
    out = run(spec_path=a.spec, filter_json=a.filter_json, duration_s=a.duration_s, seed=a.seed, vehicle=a.vehicle,
              physics=not a.no_physics)
    print("| chain | flown as | attitude RMS, deg | motor noise, N | gyro delay, ms |")
    print("|---|---|---|---|---|")
    for k, r in out["rows"].items():
        print(f"| {k} | {' -> '.join(r['chain']) or 'none'} | {r['att_rms_deg']:.3f} | {r['motor_noise_n']:.4f} | {r['delay_ms']:.2f} |"
              + (" crashed" if r["crashed"] else ""))
    print(out["caveat"])


if __name__ == "__main__":
    main()
