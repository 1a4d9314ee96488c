"""Attitude integration benchmark: vectorised exact integration vs a per-sample loop.

Run: ``nice python bench/bench_attitude.py [--n N] [--loop-n M]``. Prints, from one run on the
same data, the samples/s of :func:`gyrocore.attitude.integrate_gyro` (vectorised, blockwise
prefix product) and of :func:`gyrocore.attitude.integrate_gyro_loop` (plain per-sample loop of
the same exact exponential step), and the largest attitude difference between them in rad.
``--loop-n`` limits the (~20× slower) loop to the first samples.
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np

from gyrocore.attitude import error_angle_rad, integrate_gyro, integrate_gyro_loop


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=3_600_000, help="samples (default: 1 h at 1 kHz)")
    ap.add_argument("--loop-n", type=int, default=None, help="samples for the reference loop (default: all)")
    ap.add_argument("--rate-hz", type=float, default=1000.0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    t = np.arange(args.n) / args.rate_hz
    # hover-like motion: slow sinusoidal manoeuvres + rotor-like vibration + noise, rad/s
    w = (
        0.5 * np.sin(2 * np.pi * 0.2 * t)[:, None] * np.array([1.0, 0.7, 0.3])
        + 0.2 * np.sin(2 * np.pi * 150 * t)[:, None]
        + rng.normal(0.0, 0.05, (args.n, 3))
    )

    integrate_gyro(t[:1000], w[:1000])  # warm up
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        q_vec = integrate_gyro(t, w)
        best = min(best, time.perf_counter() - t0)
    m = args.n if args.loop_n is None else min(args.loop_n, args.n)
    t0 = time.perf_counter()
    q_loop = integrate_gyro_loop(t[:m], w[:m])
    t_loop = time.perf_counter() - t0
    diff = float(np.max(error_angle_rad(q_vec[:m], q_loop)))
    print(
        f"machine: {platform.processor() or platform.machine()}, python {platform.python_version()}, numpy {np.__version__}"
    )
    print(
        f"vectorised integrate_gyro : {args.n:>9d} samples in {best:7.3f} s = {args.n / best / 1e6:6.2f} M samples/s (best of 3)"
    )
    print(f"per-sample loop           : {m:>9d} samples in {t_loop:7.3f} s = {m / t_loop / 1e6:6.2f} M samples/s")
    print(f"speed-up                  : {(args.n / best) / (m / t_loop):.1f}x")
    print(f"max |attitude difference| over the first {m} samples: {diff:.3e} rad (goal < 1e-9)")


if __name__ == "__main__":
    main()
