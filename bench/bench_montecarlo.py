"""Monte Carlo speed-up: the same campaign on 1 and on K local workers, side by side.

Run: ``nice python bench/bench_montecarlo.py [--scenarios a,b] [--sensors p] [--instances 8]
[--duration-s 20] [--workers 2] [--quick] [--dask] [--json]``.

The same tasks (same seed) run serially (1 worker, in this process), on ``--workers`` local
processes, and optionally (``--dask``) on a ``dask.distributed.LocalCluster`` with the same
number of single-threaded worker processes. Prints each wall time, the speed-up over the
serial run and whether the results are bit-identical (they must be: a task's seed depends
only on the campaign seed and its instance number). Process start-up (spawn, imports) is
inside the timed region: it is part of what a user waits for. CPU seconds are shown beside
the wall time (this process for the serial run; the reaped worker processes for the others,
including their start-up): on a shared machine the wall-time speed-up is bounded by the CPU
the other users leave ("cores obtained" = CPU seconds / wall seconds), and the CPU ratio
shows the parallel overhead.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import time

import numpy as np

from experiments import montecarlo as mc


def _cpu_self() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _cpu_children() -> float:
    """CPU time of reaped child processes (pool workers; Dask nannies and their workers)."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _load() -> str:
    return " ".join(open("/proc/loadavg").read().split()[:3])


def _identical(a: mc.CampaignResult, b: mc.CampaignResult) -> bool:
    ma = np.array([[v for _, v in r.metrics] for r in a.tasks])
    mb = np.array([[v for _, v in r.metrics] for r in b.tasks])
    return ma.shape == mb.shape and bool(np.array_equal(ma, mb, equal_nan=True))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", default=None, help="comma list (default: every scenario)")
    ap.add_argument("--sensors", default=None, help="comma list (default: every preset)")
    ap.add_argument("--instances", type=int, default=4)
    ap.add_argument("--duration-s", type=float, default=None)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="the tasks' short calibration runs (option quick=True)")
    ap.add_argument("--dask", action="store_true", help="also run on a LocalCluster")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    scen, sens = mc.resolve_names(
        scenarios=None if a.scenarios is None else a.scenarios.split(","),
        sensors=None if a.sensors is None else a.sensors.split(","),
    )
    kw = dict(
        scenarios=scen,
        sensors=sens,
        instances=a.instances,
        seed=a.seed,
        duration_s=a.duration_s,
        options={"quick": True} if a.quick else None,
    )
    n_tasks = len(scen) * len(sens) * a.instances
    load0 = _load()
    runs, cpu = {}, {}
    c0 = _cpu_self()
    runs["serial"] = mc.run_campaign(workers=1, **kw)
    cpu["serial"] = _cpu_self() - c0
    c0 = _cpu_children()
    runs[f"processes x{a.workers}"] = mc.run_campaign(workers=a.workers, **kw)
    cpu[f"processes x{a.workers}"] = _cpu_children() - c0
    if a.dask:
        from dask.distributed import LocalCluster

        t0 = time.perf_counter()
        c0 = _cpu_children()
        with LocalCluster(
            n_workers=a.workers, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=50
        ) as cluster:
            start_s = time.perf_counter() - t0
            runs[f"dask LocalCluster x{a.workers}"] = mc.run_campaign(scheduler=cluster.scheduler_address, **kw)
        cpu[f"dask LocalCluster x{a.workers}"] = _cpu_children() - c0
    base = runs["serial"]
    out = {
        "machine": {"nproc": os.cpu_count(), "python": platform.python_version(), "numpy": np.__version__},
        "tasks": n_tasks,
        "scenarios": scen,
        "sensors": sens,
        "instances": a.instances,
        "duration_s": a.duration_s,
        "quick": a.quick,
        "runs": {
            k: {
                "wall_s": r.wall_s,
                "speedup_vs_serial": base.wall_s / r.wall_s,
                "identical_to_serial": _identical(base, r),
                "cpu_s": cpu[k],
                "cpu_over_serial_cpu": cpu[k] / cpu["serial"],
                "cores_obtained": cpu[k] / r.wall_s,
                "backend": r.backend,
                "workers": r.workers,
            }
            for k, r in runs.items()
        },
    }
    if a.dask:
        out["dask_cluster_start_s"] = start_s
    if a.json:
        print(json.dumps(out, indent=1))
    else:
        print(
            f"Monte Carlo campaign: {n_tasks} tasks ({len(scen)} scenario(s) x {len(sens)} sensor(s) x "
            f"{a.instances} instances), duration {a.duration_s or 'default'}"
        )
        for k, v in out["runs"].items():
            print(
                f"  {k:<26s} wall {v['wall_s']:7.1f} s  speed-up {v['speedup_vs_serial']:.2f}x  "
                f"CPU {v['cpu_s']:7.1f} s ({v['cpu_over_serial_cpu']:.2f}x serial, {v['cores_obtained']:.2f} cores obtained)  "
                f"identical to serial: {v['identical_to_serial']}"
            )
        print(f"  load average before/after: {load0} / {_load()}")
        if a.dask:
            print(f"  (LocalCluster start-up, not timed above: {start_s:.1f} s)")
    return 0 if all(v["identical_to_serial"] for v in out["runs"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
