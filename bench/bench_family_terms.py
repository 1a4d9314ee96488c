"""Cost of a registry family term (``periodic[...]`` etc.) in the closed-loop hover.

Run: ``python bench/bench_family_terms.py [--hover-s 10] [--repeat 3]`` (prints one table).

Family terms of time alone (periodic, step, ``regressor[t]``) are tabulated before the flight
and added by the numba kernels; any other family term (of the rate, the specific force, the
temperature) sends ``fly_hover`` to its Python loop, where the term is one generic per-step
call (the batch path's numpy term on a one-sample input; bit-identical to
``SyntheticGyro.measure`` either way). Four flights of the same unit (ICM-42688-P preset,
physics and gyro 1 kHz, vibration on), side by side in one run: (a) the preset's catalogue
effects on the compiled kernels, (b) (a) plus ``periodic[37.5]`` (compiled, tabulated),
(c) the catalogue on the Python loop (``fly_hover(compiled=False)``), (d) (a) plus
``regressor[omega_x*f_z]`` (Python loop, by necessity). (c)/(a) is the price of leaving the
kernels, (d)/(c) the per-step family call's own.
Best of ``--repeat``, CPU time of this process (steadier than wall time on a shared machine).
"""

from __future__ import annotations

import argparse
import time

from sim import quadrotor as Q
from sim.gyro import SyntheticGyro

TERM = {"periodic[37.5]": {"a_cos_rad_s": [0.01, 0.0, 0.0]}}
RATE_TERM = {"regressor[omega_x*f_z]": {"coef": [0.0, 1e-3, 0.0]}}


def _fly(overrides: dict, compiled: bool, hover_s: float) -> tuple[float, float]:
    g = SyntheticGyro("icm42688p", rate_hz=1000.0, seed=1, overrides=overrides)
    st = g.stream(int(round(hover_s * 1000.0)))
    c0, w0 = time.process_time(), time.perf_counter()
    Q.fly_hover(duration_s=hover_s, gyro=st, seed=1, compiled=compiled)
    return time.process_time() - c0, time.perf_counter() - w0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hover-s", type=float, default=10.0)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    _fly({}, True, 1.0)  # load the numba kernels once (not timed)
    cases = (
        ("(a) catalogue, compiled kernels", {}, True),
        ("(b) + periodic[37.5], compiled", TERM, True),
        ("(c) catalogue, Python loop", {}, False),
        ("(d) + regressor[omega_x*f_z], Python", RATE_TERM, True),
    )
    best = {}
    for _ in range(a.repeat):
        for label, ov, comp in cases:
            c, w = _fly(ov, comp, a.hover_s)
            b = best.get(label)
            best[label] = (min(c, b[0]), min(w, b[1])) if b else (c, w)
    print(f"hover {a.hover_s:g} s, best of {a.repeat}")
    print(f"{'case':36s} {'cpu s':>7s} {'wall s':>7s} {'cpu / (a)':>9s}")
    ca = best[cases[0][0]][0]
    for label, _, _ in cases:
        c, w = best[label]
        print(f"{label:36s} {c:7.2f} {w:7.2f} {c / ca:9.2f}")


if __name__ == "__main__":
    main()
