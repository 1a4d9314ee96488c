#!/usr/bin/env python3
"""A deliberately wrong calibrator, for the gate to fail (docs/score.md).

    python wrong_calibrator.py fit PARAMS IN...           (nothing to fit)
    python wrong_calibrator.py apply PARAMS IN OUT --mistake sign|units

``sign``: the power-up bias (mean of the first 2 s) is *added* instead of subtracted, so the
bias doubles — a plausible-looking file the gate must fail on its bounds. ``units``: the right
correction written in deg/s into the rad/s columns — the harness detects it from the data
(corrected rate ≈ 57.3 × the raw one) and records every unit as failed.
"""

import argparse
import math
import sys

import numpy as np


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("step", choices=["fit", "apply"])
    ap.add_argument("files", nargs="+")
    ap.add_argument("--mistake", choices=["sign", "units"], default="sign")
    a = ap.parse_args(argv)
    if a.step == "fit":
        open(a.files[0], "w").write("nothing\n")
        return 0
    _, inp, out = a.files
    lines = [ln for ln in open(inp, encoding="utf-8") if not ln.startswith("#")]
    header = lines[0].strip().split(",")
    d = np.loadtxt(lines[1:], delimiter=",", ndmin=2)
    t = d[:, header.index("t_s")]
    g = d[:, [header.index(f"gyro_{x}_rad_s") for x in "xyz"]]
    n = int(round(2.0 * (t.size - 1) / (t[-1] - t[0])))
    b = g[:n].mean(axis=0)
    w = g + b if a.mistake == "sign" else (g - b) * 180.0 / math.pi
    with open(out, "w", encoding="utf-8") as fh:
        fh.write("t_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s\n")
        np.savetxt(fh, np.column_stack([t, w]), delimiter=",", fmt="%.17g")
    return 0


if __name__ == "__main__":
    sys.exit(main())
