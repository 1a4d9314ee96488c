"""The residual loop (catalogue + open search) on a one-hour 1 kHz recording: time and peak memory.

Each stage runs in its own fresh subprocess (peak RSS = ``ru_maxrss`` of that process), so the
figures do not include another stage's memory:

* ``synth``: only build the recording (:func:`experiments.close_the_loop.synthetic_recording`,
  tumbling reference, white + flicker + RRW + Gauss–Markov noise) — the baseline;
* ``loop``: the same recording, then :func:`gyrocore.loop.loop.run_loop` with the open search
  (declared: bias);
* ``loop_catalogue``: the same with ``open_search=False`` (the catalogue alone, for the ratio).

Usage: ``python bench/bench_loop.py [--duration-s 3600] [--rate-hz 1000] [--stages synth,loop,loop_catalogue]``
Prints one Markdown row per stage: wall and CPU seconds of the loop call, peak RSS, load average.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

CHILD = r"""
import json, os, resource, sys, time
from experiments.close_the_loop import OPEN_NOISE, effect_params, synthetic_recording
stage, dur, rate = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
rec = synthetic_recording({"bias": effect_params("bias")}, seed=1, duration_s=dur, rate_hz=rate, **OPEN_NOISE)
rss_data = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
out = {"stage": stage, "n": rec.n, "rss_after_data_mib": rss_data}
if stage != "synth":
    from threadpoolctl import threadpool_limits
    threadpool_limits(limits=1, user_api="blas")
    from gyrocore.loop.loop import run_loop
    t0, c0 = time.perf_counter(), time.process_time()
    r = run_loop(rec, declared=["bias"], open_search=(stage == "loop"))
    out.update(wall_s=time.perf_counter() - t0, cpu_s=time.process_time() - c0, found=r.found_effects,
               unexplained=[u.effect for u in r.unexplained], n_windows=r.n_windows)
out["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(out))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration-s", type=float, default=3600.0)
    ap.add_argument("--rate-hz", type=float, default=1000.0)
    ap.add_argument("--stages", default="synth,loop,loop_catalogue")
    a = ap.parse_args()
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    print(
        "| stage | samples | loop wall, s | loop CPU, s | peak RSS, MiB | RSS after the data, MiB | found / unexplained | load (1 min) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for st in a.stages.split(","):
        t0 = time.time()
        p = subprocess.run(
            [sys.executable, "-c", CHILD, st, str(a.duration_s), str(a.rate_hz)],
            env=env,
            capture_output=True,
            text=True,
        )
        if p.returncode != 0:
            print(f"| {st} | failed: {p.stderr.strip().splitlines()[-1] if p.stderr.strip() else p.returncode} |")
            continue
        d = json.loads(p.stdout.strip().splitlines()[-1])
        load = os.getloadavg()[0]
        fu = (
            "—"
            if st == "synth"
            else f"{', '.join(d['found']) or 'nothing'} / {', '.join(d['unexplained']) or 'nothing'}"
        )
        wall = "—" if st == "synth" else f"{d['wall_s']:.1f}"
        cpu = "—" if st == "synth" else f"{d['cpu_s']:.1f}"
        print(
            f"| {st} | {d['n']} | {wall} | {cpu} | {d['peak_rss_mib']:.0f} | {d['rss_after_data_mib']:.0f} | {fu} | "
            f"{load:.1f} |",
            flush=True,
        )
        del t0


if __name__ == "__main__":
    main()
