"""Benchmark: our overlapping-ADEV kernel vs ``allantools.oadev`` on the same 10⁷ samples.

Prints, from one run on the same data and the same octave τ list: the wall time of each
(best of ``--repeat``), their ratio, the largest relative difference of the deviations, and
the time of the whole per-axis analysis (deviation + EDF + joint IEEE 952 fit).

    nice python bench/bench_allan.py [--n 10000000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=10_000_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--rate-hz", type=float, default=1000.0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    import allantools

    from gyrocore.noise import allan as AL
    from gyrocore.noise import adev as ADEV
    from gyrocore.data.recording import Recording

    rng = np.random.default_rng(args.seed)
    fs = args.rate_hz
    N, K = 0.003, 1e-4
    y = N * math.sqrt(fs) * rng.standard_normal(args.n) + np.cumsum(rng.standard_normal(args.n)) * K / math.sqrt(fs)
    m = ADEV.octave_m(args.n)
    taus = m / fs

    def best(f):
        ts, out = [], None
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            out = f()
            ts.append(time.perf_counter() - t0)
        return min(ts), out

    # interleaved (A, B, A, B, ...) so that load from other processes hits both alike
    t_at = t_ours = float("inf")
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        tau_a, dev_a, _e, ns_a = allantools.oadev(y, rate=fs, data_type="freq", taus=taus)
        t_at = min(t_at, time.perf_counter() - t0)
        t0 = time.perf_counter()
        tau_o, dev_o, ns_o = ADEV.oadev(y, fs, m, engine="fast")
        t_ours = min(t_ours, time.perf_counter() - t0)
    assert np.array_equal(np.asarray(ns_a, dtype=np.int64), ns_o) and np.allclose(tau_a, tau_o, rtol=1e-15)
    rel = float(np.max(np.abs(dev_o / dev_a - 1.0)))
    rec = Recording(t_s=np.arange(args.n) / fs, gyro_rad_s=np.column_stack([y, y, y]))
    t_full, res = best(lambda: AL.allan_analysis(rec, axes=("x",)))
    r = res.axes["x"]
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, numpy {np.__version__}, "
        f"allantools {allantools.__version__}"
    )
    print(
        f"data: {args.n} samples at {fs:g} Hz, {m.size} octave taus ({taus[0]:g} .. {taus[-1]:g} s), "
        f"best of {args.repeat}, interleaved; both times include the rate-to-angle integration"
    )
    print(f"allantools.oadev          : {t_at:8.3f} s")
    print(f"gyrocore.noise.adev.oadev fast : {t_ours:8.3f} s   speed-up x{t_at / t_ours:.2f}")
    print(f"max relative difference   : {rel:.3e}")
    print(
        f"full analysis of one axis (ADEV + EDF + joint fit): {t_full:.3f} s; "
        f"N = {r.all_terms()['arw_rad_per_sqrt_s']} (true {N}), K = {r.all_terms()['rrw_rad_per_s_sqrt_s']} (true {K})"
    )


if __name__ == "__main__":
    main()
