#!/usr/bin/env python3
"""A test routine for the command protocol: behaves well or fails in a chosen way.

    routine_probe.py fit PARAMS IN... [--mode M]
    routine_probe.py apply PARAMS IN OUT [--mode M]

Modes (apply step unless named): ok (bias = mean of the first 100 samples), crash, hang, nothing,
nan, rows, degs, fit-crash, every-second-crash (uses $PROBE_STATE as a counter file).
With $PROBE_OUT set, each step appends a JSON line describing what it was given (argv, cwd, the
files in cwd, each CSV's header and metadata keys).
"""

import json
import os
import sys
import time

import numpy as np


def describe(path):
    meta, header = [], None
    with open(path, encoding="utf-8") as fh:
        for ln in fh:
            if ln.startswith("#"):
                meta.append(ln[1:].split(":", 1)[0].strip())
            else:
                header = ln.strip().split(",")
                break
    return {"path": path, "meta": meta, "header": header}


def main(argv):
    mode = "ok"
    if "--mode" in argv:
        i = argv.index("--mode")
        mode = argv[i + 1]
        argv = argv[:i] + argv[i + 2 :]
    step, files = argv[0], argv[1:]
    if os.environ.get("PROBE_OUT"):
        csvs = [describe(f) for f in files if f.endswith(".csv") and os.path.isfile(f)]
        with open(os.environ["PROBE_OUT"], "a", encoding="utf-8") as fh:
            fh.write(
                json.dumps(
                    {"step": step, "argv": argv, "cwd": os.getcwd(), "listing": sorted(os.listdir(".")), "csvs": csvs}
                )
                + "\n"
            )
    if step == "fit":
        if mode == "fit-crash":
            print("cannot fit: table run has no still part", file=sys.stderr)
            return 4
        with open(files[0], "w", encoding="utf-8") as fh:
            fh.write("ok\n")
        return 0
    params, inp, out = files
    assert open(params, encoding="utf-8").read() == "ok\n"
    if mode == "crash":
        print("Traceback (most recent call last):\nZeroDivisionError: division by zero", file=sys.stderr)
        return 3
    if mode == "every-second-crash":
        state = os.environ["PROBE_STATE"]
        n = int(open(state).read()) if os.path.exists(state) else 0
        open(state, "w").write(str(n + 1))
        if n % 2 == 1:
            print("segfault-like failure", file=sys.stderr)
            return 139
    if mode == "hang":
        time.sleep(600)
    if mode == "nothing":
        return 0
    lines = [ln for ln in open(inp, encoding="utf-8") if not ln.startswith("#")]
    header = lines[0].strip().split(",")
    d = np.loadtxt(lines[1:], delimiter=",", ndmin=2)
    t = d[:, header.index("t_s")]
    g = d[:, [header.index(f"gyro_{x}_rad_s") for x in "xyz"]]
    w = g - g[:100].mean(axis=0)
    if mode == "nan":
        w[5, 1] = np.nan
    if mode == "rows":
        t, w = t[:-1], w[:-1]
    if mode == "degs":
        w = np.degrees(w)
    with open(out, "w", encoding="utf-8") as fh:
        fh.write("t_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s\n")
        np.savetxt(fh, np.column_stack([t, w]), delimiter=",", fmt="%.17g")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
