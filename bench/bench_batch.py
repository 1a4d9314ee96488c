"""``gyroharness batch`` throughput: files per second at 1 and 2 local Dask workers, side by side.

Run: ``nice python bench/bench_batch.py [--units 24] [--duration-s 120] [--rate-hz 1000]
[--command allan] [--work DIR] [--json]``.

A fleet of simulated ICM-42688-P units (``static`` scenario, seeds 0..units−1, from the
preset; written once) is processed by :func:`gyrocore.fleet.run_batch` three ways in
one run: in this process (``--workers 0``, no Dask: the reference), on a ``LocalCluster`` of
1 worker and of 2 workers (single-threaded worker processes). Each is timed twice: the whole
call (cluster start-up + tasks + table + plot) and the tasks alone (``execute`` on a cluster
already running is not separated by the API, so the start-up is measured on its own with an
empty task list and subtracted). The tables are checked to hold identical numbers.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def make_fleet(folder: Path, units: int, duration_s: float, rate_hz: float) -> list[str]:
    from gyrocore.data.recording import write_recording
    from sim import scenarios as S

    spec = S.load_scenario("static")
    paths = []
    for k in range(units):
        p = folder / f"unit{k:03d}.csv"
        if not p.exists():
            r = S.simulate(spec, sensor="icm42688p", duration_s=duration_s, seed=k, gyro_rate_hz=rate_hz)
            write_recording(r.recording, p)
        paths.append(str(p))
    return paths


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--units", type=int, default=24)
    ap.add_argument("--duration-s", type=float, default=120.0)
    ap.add_argument("--rate-hz", type=float, default=1000.0)
    ap.add_argument("--command", default="allan")
    ap.add_argument("--work", default=None)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    from gyrocore.fleet import _execute_dask, run_batch

    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="bench_batch_"))
    (work / "fleet").mkdir(parents=True, exist_ok=True)
    try:
        t0 = time.perf_counter()
        files = make_fleet(work / "fleet", a.units, a.duration_s, a.rate_hz)
        t_make = time.perf_counter() - t0
        size = sum(os.path.getsize(f) for f in files)
        runs = {}
        tables = {}
        for label, workers in (("in-process", 0), ("dask 1 worker", 1), ("dask 2 workers", 2)):
            startup = 0.0
            if workers:
                t0 = time.perf_counter()
                _execute_dask([], workers, None, lambda r: r)  # cluster start + close alone
                startup = time.perf_counter() - t0
            table = work / f"t_{workers}.csv"
            if table.exists():
                table.unlink()
            load0 = os.getloadavg()[0]
            t0 = time.perf_counter()
            summary = run_batch(
                a.command, files, table=str(table), plot=None, options={}, workers=workers, scheduler=None, resume=False
            )
            wall = time.perf_counter() - t0
            tasks = max(wall - startup, 1e-9)
            runs[label] = {
                "workers": workers,
                "wall_s": wall,
                "startup_s": startup,
                "tasks_s": tasks,
                "files_per_s": len(files) / wall,
                "files_per_s_tasks": len(files) / tasks,
                "failed": summary["n_failed"],
                "load_start": load0,
                "load_end": os.getloadavg()[0],
            }
            import pandas as pd

            tables[label] = pd.read_csv(table).sort_values("file")
        ref = tables["in-process"]
        cols = [c for c in ref.columns if c.startswith("arw_") or c.startswith("bias_")]
        same = all(np.array_equal(ref[cols].to_numpy(), t[cols].to_numpy(), equal_nan=True) for t in tables.values())
        base = runs["dask 1 worker"]["files_per_s_tasks"]
        out = {
            "units": a.units,
            "duration_s": a.duration_s,
            "rate_hz": a.rate_hz,
            "command": a.command,
            "fleet_bytes": size,
            "make_fleet_s": t_make,
            "runs": runs,
            "identical_tables": same,
            "speedup_2_over_1_tasks": runs["dask 2 workers"]["files_per_s_tasks"] / base,
            "speedup_2_over_1_wall": runs["dask 2 workers"]["files_per_s"] / runs["dask 1 worker"]["files_per_s"],
            "cores": len(os.sched_getaffinity(0)),
        }
    finally:
        if not a.work:
            shutil.rmtree(work, ignore_errors=True)
    if a.json:
        print(json.dumps(out, indent=1))
    else:
        print(
            f"batch {a.command}: {a.units} units x {a.duration_s:g} s at {a.rate_hz:g} Hz "
            f"({size / 2**20:.0f} MiB of CSV; simulated in {t_make:.0f} s); {out['cores']} cores"
        )
        print(f"{'backend':<16s} {'wall s':>8s} {'start s':>8s} {'files/s':>8s} {'files/s (tasks)':>16s} {'load':>10s}")
        for k, r in runs.items():
            print(
                f"{k:<16s} {r['wall_s']:8.1f} {r['startup_s']:8.1f} {r['files_per_s']:8.2f} {r['files_per_s_tasks']:16.2f} "
                f"{r['load_start']:4.1f}->{r['load_end']:.1f}"
            )
        print(
            f"2 workers over 1: {out['speedup_2_over_1_tasks']:.2f}x (tasks), {out['speedup_2_over_1_wall']:.2f}x (wall); "
            f"tables identical: {same}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
