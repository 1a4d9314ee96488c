"""Campaign throughput of `gyroharness run`'s two big campaigns, this tree beside another commit.

Run: ``nice python bench/bench_campaigns.py [--baseline COMMIT] [--units 1] [--replicas 39]
[--repeat 2] [--json]``.

* **ablation**: unit-scenarios per core-minute — ``--units`` sensor units through the six
  scenarios of the ablation (:func:`experiments.ablation.ablation_task`) with the standard size of
  ``gyroharness run`` (the quick calibration runs, :data:`experiments.ablation.STANDARD_DURATIONS_S`),
  serially in one process (calibration included: the first scenario of a unit calibrates it,
  the others reuse it, as in the campaign).
* **twin**: replica-statistics per core-second — the twin of one real set (tomisuarez2 static 449 s,
  ../shared/data) with ``--replicas`` replicas; a replica-statistic is one statistic value (one bin
  of one statistic) evaluated on one replica: replicas × the bins of every statistic, twice when the
  twin was closed (replayed again with the added terms).

Each measurement runs in a fresh interpreter (``python -c``) with the tree on ``PYTHONPATH``; the
baseline tree is ``git archive COMMIT`` unpacked into a temporary folder. The two trees alternate
(baseline, this tree, baseline, ...) ``--repeat`` times and the least CPU time (user + system of
the child) of each is kept, so a load change during the run hits both. CPU time, not wall time:
the machine is shared. Results of the two trees are printed side by side with their ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: main before the campaign speed-ups of `gyroharness run`'s standard size
DEFAULT_BASELINE = "89d344d"

_ABLATION = r"""
import json, sys, tempfile, time, warnings
from experiments.montecarlo import make_tasks
from experiments.ablation import ablation_task, SCENARIOS
durs = {"static": 60.0, "static_bumped": 30.0, "turntable": 120.0, "thermal": 300.0, "hover": 15.0, "power_cycles": 60.0}
tasks = make_tasks(scenarios=SCENARIOS, sensors=("icm42688p",), instances=int(sys.argv[1]), seed=0, duration_s=None,
                   options={"quick": True, "cache_dir": tempfile.mkdtemp(), "durations": tuple(durs.items())})
out = [ablation_task(t) for t in tasks]
print(json.dumps({"unit_scenarios": len(out), "all_final_deg": [dict(r.metrics).get("all__final_deg") for r in out]}))
"""

_TWIN = r"""
import json, sys, warnings
from pathlib import Path
from experiments import twin as T
p = Path(sys.argv[2]) / "tomisuarez2_mpu6050/example_data_tinit_calc.csv"
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    rec, segs = T.load_recording(p)
    r = T.twin(rec, segments=segs, n_replicas=int(sys.argv[1]), seed=0, file=str(p))
d = r.to_json()
# statistic values compared per replica: every bin of every statistic, twice when the twin was closed
n_stat = sum(int(s["n_bins"]) for s in d["statistics"].values()) * (2 if "after" in d else 1)
print(json.dumps({"replicas": int(sys.argv[1]), "statistics": n_stat, "distance": d["twin_distance"]}))
"""


def _tree(commit: str, tmp: Path) -> Path:
    dest = tmp / commit
    dest.mkdir()
    data = subprocess.run(
        ["git", "-C", str(ROOT), "archive", "--format=tar", commit], check=True, capture_output=True
    ).stdout
    arch = tmp / f"{commit}.tar"
    arch.write_bytes(data)
    with tarfile.open(arch) as tf:
        tf.extractall(dest, filter="data")
    return dest


def _measure(tree: Path, code: str, *args: str) -> tuple[float, dict]:
    env = {
        **os.environ,
        "PYTHONPATH": str(tree),
        "OMP_NUM_THREADS": "1",
        "OPENBLAS_NUM_THREADS": "1",
        "MKL_NUM_THREADS": "1",
    }
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    p = subprocess.run([sys.executable, "-c", code, *args], cwd=tree, env=env, capture_output=True, text=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise SystemExit(f"error: benchmark failed in {tree}: {p.stderr.strip().splitlines()[-1:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return cpu, json.loads(p.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", default=DEFAULT_BASELINE, help="commit to compare with (default: %(default)s)")
    ap.add_argument("--units", type=int, default=1, help="ablation units (x 6 scenarios)")
    ap.add_argument("--replicas", type=int, default=39, help="twin replicas")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        trees = {"baseline " + a.baseline: _tree(a.baseline, Path(tmp)), "this tree": ROOT}
        best: dict = {}
        for _ in range(a.repeat):
            for label, tree in trees.items():
                for name, code, args in (
                    ("ablation", _ABLATION, (str(a.units),)),
                    ("twin", _TWIN, (str(a.replicas), a.data)),
                ):
                    cpu, res = _measure(tree, code, *args)
                    key = (label, name)
                    if key not in best or cpu < best[key][0]:
                        best[key] = (cpu, res)
    labels = list(trees)
    out = {"baseline": a.baseline, "units": a.units, "replicas": a.replicas, "repeat": a.repeat}
    for name in ("ablation", "twin"):
        row = {}
        for label in labels:
            cpu, res = best[(label, name)]
            if name == "ablation":
                row[label] = {
                    "cpu_s": cpu,
                    "unit_scenarios_per_core_min": res["unit_scenarios"] / cpu * 60.0,
                    "all_final_deg": res["all_final_deg"],
                }
            else:
                n = res["replicas"] * max(res["statistics"], 1)
                row[label] = {"cpu_s": cpu, "replica_statistics_per_core_s": n / cpu, "statistics": res["statistics"]}
        k = "unit_scenarios_per_core_min" if name == "ablation" else "replica_statistics_per_core_s"
        row["ratio"] = row[labels[1]][k] / row[labels[0]][k]
        if name == "ablation":
            row["same_results"] = row[labels[0]]["all_final_deg"] == row[labels[1]]["all_final_deg"]
        out[name] = row
    if a.json:
        print(json.dumps(out, indent=2))
    else:
        for name in ("ablation", "twin"):
            row = out[name]
            k = "unit_scenarios_per_core_min" if name == "ablation" else "replica_statistics_per_core_s"
            print(
                f"{name:9s} "
                + "  ".join(f"{lab}: {row[lab][k]:.3g} ({row[lab]['cpu_s']:.1f} s CPU)" for lab in labels)
                + f"  ratio {row['ratio']:.2f}"
                + (f"  same results: {row['same_results']}" if "same_results" in row else "")
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
