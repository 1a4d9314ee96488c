#!/usr/bin/env python3
"""The source article's calibration as an external program (gyroharness command protocol).

    python article_cmd.py fit PARAMS TABLE.csv [THERMAL.csv] [--lsb-per-dps 131]
    python article_cmd.py apply PARAMS IN.csv OUT.csv [--lsb-per-dps 131]

numpy only; it knows nothing of gyroharness but the data file (DESIGN.md: ``#`` metadata lines,
a header with unit-suffixed names). The method (ARTICLE.md §1, §5): power-up bias b = mean of
the first 200 samples whose motion sum Σ|g[k] − g[k−1]| stays within 500 raw counts per axis;
M = C·B⁻¹ from the rate table's rotations (B = ∫(ω̂ − b)dt per rotation, C = ∫ω_table dt;
with more than three rotations, the least-squares M = (Σ C Bᵀ)(Σ B Bᵀ)⁻¹); ω = M·(ω̂ − b).
The thermal run is not used (the article has no thermal model). Run it with
``gyroharness score --fit-cmd "python article_cmd.py fit {params} {inputs} --lsb-per-dps 16.4"
--apply-cmd "python article_cmd.py apply {params} {input} {output} --lsb-per-dps 16.4"``.
"""

import argparse
import json
import math
import sys

import numpy as np

WINDOW, THRESHOLD_COUNTS, SEARCH_S, PAD = 200, 500.0, 30.0, 50


def read(path):
    with open(path, encoding="utf-8") as fh:
        lines = [ln for ln in fh if not ln.startswith("#")]
    header = lines[0].strip().split(",")
    data = np.loadtxt(lines[1:], delimiter=",", ndmin=2)
    return {h: data[:, i] for i, h in enumerate(header)}


def cols(d, names):
    return np.column_stack([d[n] for n in names])


def powerup_bias(g, lsb_rad_s, rate_hz):
    n_search = int(min(g.shape[0], max(WINDOW, SEARCH_S * rate_hz)))
    counts = g[:n_search] / lsb_rad_s
    for a in range(0, n_search - WINDOW + 1, WINDOW):
        if np.all(np.abs(np.diff(counts[a : a + WINDOW], axis=0)).sum(axis=0) <= THRESHOLD_COUNTS):
            return g[a : a + WINDOW].mean(axis=0)
    return g[:WINDOW].mean(axis=0)


def rate_of(t):
    return (t.size - 1) / (t[-1] - t[0])


def fit(params_path, inputs, lsb):
    d = read(inputs[0])  # the rate-table run
    t = d["t_s"]
    g = cols(d, ["gyro_x_rad_s", "gyro_y_rad_s", "gyro_z_rad_s"])
    r = cols(d, ["ref_x_rad_s", "ref_y_rad_s", "ref_z_rad_s"])
    still = np.linalg.norm(r, axis=1) <= 1e-6
    b = powerup_bias(g[still], lsb, rate_of(t))
    gb = g - b
    moving = (~still).astype(np.int8)
    edges = np.diff(np.concatenate([[0], moving, [0]]))
    CB, BB = np.zeros((3, 3)), np.zeros((3, 3))
    for s, e in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)):
        a, z = max(0, s - PAD), min(t.size, e + PAD)
        if z - a < 3:
            continue
        B = np.trapezoid(gb[a:z], t[a:z], axis=0)
        C = np.trapezoid(r[a:z], t[a:z], axis=0)
        CB += np.outer(C, B)
        BB += np.outer(B, B)
    M = np.linalg.solve(BB.T, CB.T).T
    with open(params_path, "w", encoding="utf-8") as fh:
        json.dump({"M": M.tolist(), "lsb_rad_s": lsb}, fh)


def apply(params_path, inp, out, lsb):
    with open(params_path, encoding="utf-8") as fh:
        p = json.load(fh)
    d = read(inp)
    t = d["t_s"]
    w = cols(d, ["gyro_x_rad_s", "gyro_y_rad_s", "gyro_z_rad_s"]).copy()
    pu = d.get("power_up_index", np.zeros(t.size))
    edges = np.concatenate([[0], np.flatnonzero(np.diff(pu) != 0) + 1, [t.size]])
    rate = rate_of(t)
    for a, z in zip(edges[:-1], edges[1:]):
        w[a:z] -= powerup_bias(w[a:z], p["lsb_rad_s"], rate)
    w = w @ np.asarray(p["M"]).T
    with open(out, "w", encoding="utf-8") as fh:
        fh.write("t_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s\n")
        np.savetxt(fh, np.column_stack([t, w]), delimiter=",", fmt="%.17g")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("step", choices=["fit", "apply"])
    ap.add_argument("files", nargs="+")
    ap.add_argument("--lsb-per-dps", type=float, default=131.0, help="sensor counts per deg/s (article: 131)")
    a = ap.parse_args(argv)
    lsb = math.pi / 180.0 / a.lsb_per_dps
    if a.step == "fit":
        fit(a.files[0], a.files[1:], lsb)
    else:
        if len(a.files) != 3:
            ap.error("apply needs PARAMS IN OUT")
        apply(*a.files, lsb)
    return 0


if __name__ == "__main__":
    sys.exit(main())
