"""Closed-loop check of ``gyroharness filter``: the candidates flown by the simulator with the
measured vibration in the loop (issue 16 item 5, first closed-loop version).

The F450 quadrotor of :func:`sim.quadrotor.fly_hover` hovers with small attitude steps; its rate
loop reads the synthetic gyro **plus** the vibration of a spec band
(:func:`gyrocore.vibration.synthesize`, the measured PSD before the firmware filters, as a
shaped Gaussian disturbance added sample by sample inside the loop) through
power-up-bias removal + the chain under test (the firmware chains of ``gyroharness filter``,
re-rated to the simulator's gyro rate). Scored as ``experiment cutoffs``: attitude tracking
error (RMS, after 1 s), motor-command noise above 20 Hz, measured gyro delay.

Caveat, said in the output: the vehicle is the F450 (no racing class yet), the vibration is
the 2.5-inch quad's, and it enters as a disturbance of the gyro, not as motion.

    python -m experiments.flight_filter --spec spec.json --filter-json filter.json [--duration-s 20] [--seed 0]
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


def fly(stages, d, *, duration_s: float, seed: int, preset: str = "icm42688p") -> dict:
    from gyrocore.filters import AffineCorrection, Pipeline, chain_filters
    from sim.controller import small_steps
    from sim.gyro import SyntheticGyro
    from sim.quadrotor import fly_hover

    n = int(math.floor(duration_s * GYRO_RATE_HZ + 1e-9))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        g = SyntheticGyro(preset, rate_hz=GYRO_RATE_HZ, seed=seed)
    flts = chain_filters(_rerated(stages, GYRO_RATE_HZ))
    pipe = Pipeline([AffineCorrection(g.power_up_bias(0)), *flts])
    truth, log = fly_hover(duration_s=duration_s, gyro=_Disturbed(g.stream(n), d), pipeline=pipe,
                           manoeuvres=small_steps(duration_s), vibration=True, seed=seed, gyro_rate_hz=GYRO_RATE_HZ)
    keep = log.t_s >= SETTLE_S
    ok = np.all(np.isfinite(log.q_WB_wxyz)) and float(np.max(log.tilt_rad())) < math.radians(60)
    nan = float("nan")
    return {"crashed": not ok,
            "att_rms_deg": float(np.degrees(np.sqrt(np.mean(log.attitude_error_rad()[keep] ** 2)))) if ok else nan,
            "motor_noise_n": log.motor_noise_n(t_from_s=SETTLE_S) if ok else nan,
            "delay_ms": 1e3 * log.gyro_delay_s() if ok else nan,
            "chain": [f.name for f in flts]}


def run(*, spec_path: str, filter_json: str, duration_s: float = 20.0, seed: int = 0, band="middle") -> dict:
    from gyrocore.vibration import read_spec, synthesize

    spec = read_spec(spec_path)
    fj = json.load(open(filter_json))
    n = int(duration_s * GYRO_RATE_HZ) + 1
    d = synthesize(spec, n=n, rate_hz=GYRO_RATE_HZ, seed=int(np.random.SeedSequence([seed, 16]).generate_state(1)[0]), band=band)
    rows = fj.get("_rows_for_sim") or []
    cands = {"none": []}
    for key in ("recommended", "as_flown", "with_rpm_filter", "article", "px4_ardupilot_lowpass"):
        if fj.get(key) and fj[key].get("stages") is not None:
            cands[key] = fj[key]["stages"]
    for k, v in fj.get("defaults", {}).items():
        if v.get("stages") is not None:
            cands[k] = v["stages"]
    out = {"spec": spec_path, "band": band, "duration_s": duration_s, "seed": seed,
           "caveat": "F450 vehicle, 2.5-inch quad's vibration as an in-loop gyro disturbance (not motion); "
                     "RPM notches not flown (the spec's lines are not tied to the F450's rotors)",
           "rows": {}}
    for name, st in cands.items():
        out["rows"][name] = fly(st, d, duration_s=duration_s, seed=seed)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", required=True)
    ap.add_argument("--filter-json", required=True)
    ap.add_argument("--duration-s", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    out = run(spec_path=a.spec, filter_json=a.filter_json, duration_s=a.duration_s, seed=a.seed)
    print("| chain | flown as | attitude RMS, deg | motor noise, N | gyro delay, ms |")
    print("|---|---|---|---|---|")
    for k, r in out["rows"].items():
        print(f"| {k} | {' -> '.join(r['chain']) or 'none'} | {r['att_rms_deg']:.3f} | {r['motor_noise_n']:.4f} | {r['delay_ms']:.2f} |"
              + (" crashed" if r["crashed"] else ""))
    print(out["caveat"])


if __name__ == "__main__":
    main()
