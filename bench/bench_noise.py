"""Speed of the full noise identification against the ADEV computation alone (goal: ≤ 2×).

Both on the same data (white N + random walk K + flicker B, three axes), timed side by side in
one run, interleaved, best of ``--repeat`` (single timings on this shared machine vary 3–10×
with the load; the ratio of the best times is the figure):

- **ADEV alone**: :func:`gyrocore.noise.adev.oadev` (fast kernel, rate → angle integration included)
  at the octave τ the old analysis used (m ≤ (n−1)/4), three axes;
- **full identification**: :func:`gyrocore.noise.allan.identify_noise` with ``method`` (the ADEV at
  every octave up to (n−1)/2, EDF, model covariance, subset selection, intervals), three axes,
  motion gate included.

Run::

    nice python bench/bench_noise.py --n 10000000 --repeat 3
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from gyrocore.noise import adev as ADEV  # noqa: E402
from gyrocore.noise import allan as AL  # noqa: E402


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=10_000_000)
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--method", default="gmwm")
    ap.add_argument("--seed", type=int, default=11)
    a = ap.parse_args(argv)
    from sim import noise as SN

    rng = np.random.default_rng(np.random.SeedSequence(a.seed))
    n, rate = a.n, a.rate
    g = SN.white_rate_noise(rng, n, rate_hz=rate, n_rad_per_sqrt_s=1e-4)
    g += SN.rate_random_walk(rng, n, rate_hz=rate, k_rad_s_per_sqrt_s=2e-6)
    g += SN.flicker_noise(rng, n, rate_hz=rate, b_rad_s=1.5e-5)
    m_old = ADEV.octave_m(n)
    t_adev, t_full, c_adev, c_full = [], [], [], []
    res = None
    # warm-up on a short slice (caches: flicker factors, EDF tables, spectral grids)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        AL.identify_noise(g[:200000], rate_hz=rate, method=a.method)
    for _ in range(a.repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        for ax in range(3):
            ADEV.oadev(g[:, ax], rate, m_old)
        t_adev.append(time.perf_counter() - t0)
        c_adev.append(time.process_time() - c0)
        t0, c0 = time.perf_counter(), time.process_time()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = AL.identify_noise(g, rate_hz=rate, method=a.method)
        t_full.append(time.perf_counter() - t0)
        c_full.append(time.process_time() - c0)
    # parts of the full identification, once each (CPU s)
    c0 = time.process_time()
    AL._judged_windows(g, rate)
    c_gate = time.process_time() - c0
    from gyrocore.noise import avar as V
    from gyrocore.noise import gmwm as G

    m_all = V.scales(n)
    c0 = time.process_time()
    curves = [ADEV.oadev(g[:, ax], rate, m_all) for ax in range(3)]
    c_adev_all = time.process_time() - c0
    c0 = time.process_time()
    for _t, d, _n in curves:
        G.fit_noise(m_all / rate, d**2, m_all, n, method=a.method)
    c_fit = time.process_time() - c0
    ba, bf = min(t_adev), min(t_full)
    ca, cf = min(c_adev), min(c_full)
    print(
        f"data: {n} samples x 3 axes at {rate:g} Hz (N = 1e-4, K = 2e-6, B = 1.5e-5), best of {a.repeat}, interleaved; "
        f"load {os.getloadavg()[0]:.1f}"
    )
    print(
        "                                                   wall s    CPU s (single-threaded: CPU time is the fair figure on a loaded machine)"
    )
    print(f"ADEV alone (fast kernel, {m_old.size} octave taus, 3 axes) : {ba:8.3f}  {ca:8.3f}")
    print(f"full identification ({a.method}, motion gate, 3 axes)    : {bf:8.3f}  {cf:8.3f}")
    print(f"ratio full / ADEV                                  : {bf / ba:8.2f}  {cf / ca:8.2f}   (goal <= 2)")
    print(
        f"  parts (CPU s): motion gate {c_gate:.3f}, ADEV at all {m_all.size} octaves {c_adev_all:.3f}, "
        f"fits (3 axes) {c_fit:.3f}"
    )
    for ax, r in res.axes.items():
        t = r.all_terms()
        print(
            f"  {ax}: N = {t['arw_rad_per_sqrt_s']}, B = {t['bias_instability_rad_s']}, "
            f"K = {t['rrw_rad_per_s_sqrt_s']}, GM = {t['correlated_sigma_rad_s']}"
        )


if __name__ == "__main__":
    main()
