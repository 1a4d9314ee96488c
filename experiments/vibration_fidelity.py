"""Fidelity of the simulated hover's gyro vibration against a real flight's (issue 16 item 3).

For each throttle band of a vibration spec (``gyroharness vibration FLIGHT -o spec.json``):
the in-band fraction (:func:`gyrocore.vibration.fidelity`: bins 40 Hz .. the spec's reliable
limit where the simulated gyro PSD is statistically indistinguishable from the real band's;
0.95 expected for a perfect match) of

* *before*: the simulated hover as it is (today's F450 vibration, physics only), and
* *after*: the same recording with the band's measured PSD added as a shaped disturbance
  (:func:`gyrocore.vibration.add_vibration`, open loop).

    python -m experiments.vibration_fidelity --spec spec.json --hover hover.csv [--t-from-s 8] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np


def run(*, spec_path: str, hover_path: str, t_from_s: float = 8.0, seed: int = 0) -> dict:
    """Table rows per band: in-band fraction and rms above 40 Hz, before and after."""
    from gyrocore.recording import read_csv
    from gyrocore.vibration import add_vibration, analyse, fidelity, read_spec

    spec = read_spec(spec_path)
    hover = read_csv(hover_path)
    before = analyse(hover, t_from_s=t_from_s)
    rows = []
    for i, b in enumerate(spec["bands"]):
        after_rec = add_vibration(hover, spec, seed=int(np.random.SeedSequence([seed, i]).generate_state(1)[0]), band=i)
        after = analyse(after_rec, t_from_s=t_from_s)
        fb, fa = fidelity(before, spec, band=i), fidelity(after, spec, band=i)
        rows.append({"band": i, "throttle": b["throttle"], "median": b["median"],
                     "before": fb, "after": fa})
    return {"spec": spec_path, "hover": hover_path, "t_from_s": t_from_s, "rows": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", required=True)
    ap.add_argument("--hover", required=True)
    ap.add_argument("--t-from-s", type=float, default=8.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    out = run(spec_path=a.spec, hover_path=a.hover, t_from_s=a.t_from_s, seed=a.seed)
    if a.json:
        print(json.dumps(out, indent=1))
        return
    d = 180 / math.pi
    print("| band (motor cmd) | axis | in-band before | in-band after | rms >40 Hz sim before / after / real, deg/s |")
    print("|---|---|---|---|---|")
    for r in out["rows"]:
        for ax in "xyz":
            b, af = r["before"][ax], r["after"][ax]
            print(f"| {r['throttle'][0]:.2f}-{r['throttle'][1]:.2f} | {ax} | {b['in_band_fraction']:.2f} | {af['in_band_fraction']:.2f} | "
                  f"{b['rms_sim_rad_s'] * d:.2f} / {af['rms_sim_rad_s'] * d:.2f} / {b['rms_real_rad_s'] * d:.2f} |")


if __name__ == "__main__":
    main()
