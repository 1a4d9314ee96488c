"""Monte Carlo campaigns: seeding, backends (serial, local processes, Dask), tables, files."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from experiments import montecarlo as mc
from gyrocore.effects import registry as E
from gyrocore.errors import GyroInputError

RATE_HZ = 200.0
N_RAD_PER_SQRT_S = 1e-3  # white noise density of the statistical task below, rad/√s


def static_bias_task(task: mc.MonteCarloTask) -> mc.TaskResult:
    """A purely statistical task (no simulator): a still gyro with a random turn-on bias and
    white noise, bias estimated as the sample mean. Module-level so that worker processes and
    Dask workers can import it."""
    rng = np.random.default_rng(task.seed)
    duration_s = task.duration_s or 2.0
    n = int(round(duration_s * RATE_HZ))
    t = np.arange(n) / RATE_HZ
    b_true = rng.normal(0.0, 0.01, size=3)
    inp = E.ModelInputs(t_s=t, omega_S_rad_s=np.zeros((n, 3)))
    clean = E.deterministic({"bias": {"b_rad_s": b_true}}, inp)
    sigma = N_RAD_PER_SQRT_S * math.sqrt(RATE_HZ)  # DESIGN.md: per-sample σ = N·√rate
    gyro = clean + rng.normal(0.0, sigma, size=(n, 3))
    err = gyro.mean(axis=0) - b_true
    scale = dict(task.options).get("scale", 1.0)
    return mc.TaskResult.from_task(
        task,
        {
            "bias_err_x_rad_s": scale * err[0],
            "bias_err_norm_rad_s": scale * float(np.linalg.norm(err)),
            "nan_metric": math.nan,
        },
    )


def _metrics_array(results):
    return np.array([[v for _, v in r.metrics] for r in results])


def _same(a, b):
    """Bit-identical results (NaN == NaN)."""
    assert [(r.index, r.scenario, r.sensor, r.instance, r.seed) for r in a] == [
        (r.index, r.scenario, r.sensor, r.instance, r.seed) for r in b
    ]
    assert np.array_equal(_metrics_array(a), _metrics_array(b), equal_nan=True)


def test_seeds_come_from_spawned_seed_sequence_and_do_not_depend_on_count():
    seeds = mc.instance_seeds(7, 5)
    children = np.random.SeedSequence(7).spawn(5)
    assert seeds == [int(c.generate_state(1, dtype=np.uint32)[0]) for c in children]
    assert mc.instance_seeds(7, 3) == seeds[:3]
    assert len(set(seeds)) == 5
    assert mc.instance_seeds(8, 5) != seeds


def test_tasks_share_instance_seeds_across_scenarios_and_sensors():
    tasks = mc.make_tasks(scenarios=["a", "b"], sensors=["p", "q"], instances=3, seed=1)
    assert [t.index for t in tasks] == list(range(12))
    by_instance = {}
    for t in tasks:
        by_instance.setdefault(t.instance, set()).add(t.seed)
    assert all(len(s) == 1 for s in by_instance.values())
    # Selecting a subset of scenarios does not change a task's seed.
    sub = mc.make_tasks(scenarios=["b"], sensors=["q"], instances=3, seed=1)
    assert [t.seed for t in sub] == [t.seed for t in tasks if t.scenario == "b" and t.sensor == "q"]


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(instances=0),
        dict(seed=-1),
        dict(scenarios=[]),
        dict(sensors=[]),
        dict(duration_s=0.0),
        dict(duration_s=float("nan")),
    ],
)
def test_bad_campaign_options_are_one_line_errors(kwargs):
    base = dict(scenarios=["s"], sensors=["p"], instances=2, seed=0)
    base.update(kwargs)
    with pytest.raises(GyroInputError) as ei:
        mc.make_tasks(**base)
    assert "\n" not in str(ei.value)


def test_serial_and_local_processes_are_identical_and_statistics_are_right():
    kw = dict(scenarios=["still"], sensors=["p"], instances=40, seed=3, duration_s=2.0, task_function=static_bias_task)
    serial = mc.run_campaign(workers=1, **kw)
    procs = mc.run_campaign(workers=2, **kw)
    assert serial.backend == "serial" and procs.backend == "processes" and procs.workers == 2
    _same(serial.tasks, procs.tasks)
    assert serial.summary == procs.summary
    # The per-axis bias error of a 2-s mean is N(0, σ_b²) with σ_b = N/√T (T = 2 s).
    # Its sample std over n = 40 instances has relative standard error ≈ 1/√(2(n−1)) = 0.113;
    # 4 standard errors: |std/σ_b − 1| < 0.46.
    s = serial.table("bias_err_x_rad_s")[("still", "p")]
    sigma_b = N_RAD_PER_SQRT_S / math.sqrt(2.0)
    assert s.n == 40
    assert abs(s.std / sigma_b - 1) < 4 / math.sqrt(2 * 39)
    x = np.array([r.metrics_dict["bias_err_x_rad_s"] for r in serial.tasks])
    assert s.median == np.median(x) and s.p90 == np.percentile(x, 90)
    nan = serial.table("nan_metric")[("still", "p")]
    assert nan.n == 0 and math.isnan(nan.median)


def test_dask_local_cluster_matches_serial_and_processes():
    distributed = pytest.importorskip("dask.distributed")
    kw = dict(
        scenarios=["still", "still2"],
        sensors=["p"],
        instances=6,
        seed=11,
        duration_s=1.0,
        task_function=static_bias_task,
        options={"scale": 2.0},
    )
    serial = mc.run_campaign(workers=1, **kw)
    procs = mc.run_campaign(workers=2, **kw)
    with distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        dashboard_address=None,
        silence_logs=50,
    ) as cluster:
        on_dask = mc.run_campaign(scheduler=cluster.scheduler_address, **kw)
    assert on_dask.backend == "dask" and on_dask.workers == 2
    _same(serial.tasks, on_dask.tasks)
    _same(procs.tasks, on_dask.tasks)
    assert serial.summary == on_dask.summary
    # options reach the task function
    assert serial.tasks[0].metrics_dict["bias_err_norm_rad_s"] > 0


def test_unreachable_scheduler_is_a_one_line_error():
    tasks = mc.make_tasks(scenarios=["s"], sensors=["p"], instances=1, seed=0)
    with pytest.raises(GyroInputError, match="cannot connect to the Dask scheduler"):
        mc.execute(static_bias_task, tasks, scheduler="tcp://127.0.0.1:9", connect_timeout_s=1.0)


def test_summary_handles_metrics_missing_in_some_tasks():
    t = mc.make_tasks(scenarios=["s"], sensors=["p"], instances=3, seed=0)
    results = [
        mc.TaskResult.from_task(t[0], {"a": 1.0, "b": 5.0}),
        mc.TaskResult.from_task(t[1], {"a": 3.0}),
        mc.TaskResult.from_task(t[2], {"a": 2.0, "b": math.inf}),
    ]
    summ = {s.metric: s for s in mc.summarise(results)}
    assert (summ["a"].n, summ["a"].median, summ["a"].mean, summ["a"].std) == (3, 2.0, 2.0, 1.0)
    # p90 of (1, 2, 3) with linear interpolation: 1 + 0.9·2 = 2.8
    assert summ["a"].p90 == pytest.approx(2.8, rel=1e-15)
    assert summ["b"].n == 1 and summ["b"].median == 5.0 and math.isnan(summ["b"].std)


def test_files_round_trip(tmp_path):
    res = mc.run_campaign(
        scenarios=["still"],
        sensors=["p", "q"],
        instances=4,
        seed=0,
        duration_s=0.5,
        workers=1,
        task_function=static_bias_task,
    )
    paths = mc.write_campaign(res, tmp_path / "mc")
    back = mc.read_campaign(tmp_path / "mc")
    _same(res.tasks, back.tasks)
    assert len(back.summary) == len(res.summary)
    for a, b in zip(res.summary, back.summary):  # NaN-aware equality (nan_metric has NaN stats)
        assert (a.scenario, a.sensor, a.metric, a.n) == (b.scenario, b.sensor, b.metric, b.n)
        assert np.array_equal([a.median, a.p90, a.mean, a.std], [b.median, b.p90, b.mean, b.std], equal_nan=True)
    md = paths["markdown"].read_text()
    assert "## still" in md and "`bias_err_x_rad_s`" in md
    rows = paths["summary_csv"].read_text().splitlines()
    assert rows[0] == "scenario,sensor,metric,n,median,p90,mean,std"
    assert len(rows) == 1 + 2 * 3
    tasks_csv = paths["tasks_csv"].read_text().splitlines()
    assert len(tasks_csv) == 1 + 8
    first = tasks_csv[1].split(",")
    assert float(first[4]) == res.tasks[0].metrics_dict["bias_err_x_rad_s"]  # repr round-trips
    doc = json.loads(paths["json"].read_text())
    doc["format_version"] = "2.0"
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(GyroInputError, match="format_version"):
        mc.read_campaign(tmp_path / "bad.json")


# ---------------------------------------------------------------------------- the command
def _cli(argv):
    """Run ``gyroharness argv`` in-process; returns (exit status, stdout, stderr)."""
    import contextlib
    import io

    from experiments.cli import build_group
    from gyrocore.cli import run_cli

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = run_cli(build_group(["experiments.commands"]), argv)
    return rc, out.getvalue(), err.getvalue()


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--scenarios", "nope", "--sensors", "icm42688p"], "unknown scenario(s) nope"),
        (["--scenarios", "static", "--sensors", "nope"], "unknown sensor(s) nope"),
        (["--scenarios", "static,static"], "duplicate names"),
        (["--instances", "0"], "--instances must be >= 1"),
        (["--workers", "0"], "--workers must be >= 1"),
        (["--workers", "2", "--scheduler", "tcp://127.0.0.1:9"], "exclude each other"),
        (["--scenarios", "static", "--sensors", "icm42688p", "--task", "nope"], "unknown Monte Carlo task 'nope'"),
    ],
)
def test_command_bad_options_are_one_line_errors(argv, message, tmp_path):
    rc, out, err = _cli(["montecarlo", *argv, "--out", str(tmp_path / "o"), "--json"])
    assert rc == 2
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0]
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_command_runs_a_real_campaign_and_writes_the_tables(tmp_path):
    rc, out, err = _cli(
        [
            "montecarlo",
            "--scenarios",
            "static",
            "--sensors",
            "icm42688p",
            "--instances",
            "2",
            "--duration-s",
            "20",
            "--quick",
            "--workers",
            "1",
            "--seed",
            "4",
            "--out",
            str(tmp_path / "mc"),
            "--json",
        ]
    )
    assert rc == 0, err
    doc = json.loads(out)
    assert doc["backend"] == "serial" and doc["instances"] == 2
    back = mc.read_campaign(tmp_path / "mc")
    assert len(back.tasks) == 2 and back.tasks[0].seed == mc.instance_seeds(4, 2)[0]
    tab = back.table("all__rms_deg")[("static", "icm42688p")]
    floor = back.table("floor__rms_deg")[("static", "icm42688p")]
    none = back.table("none__rms_deg")[("static", "icm42688p")]
    assert tab.n == 2 and floor.n == 2
    # The floor has every deterministic error removed exactly: below the raw gyro's error.
    assert floor.median < none.median


@pytest.mark.slow
def test_real_ablation_task_is_identical_on_every_backend():
    """The default task (simulate, calibrate, score) gives bit-identical results serially, on
    2 local processes and on a 2-worker Dask LocalCluster."""
    distributed = pytest.importorskip("dask.distributed")
    kw = dict(
        scenarios=["static"], sensors=["icm42688p"], instances=2, seed=9, duration_s=20.0, options={"quick": True}
    )
    serial = mc.run_campaign(workers=1, **kw)
    procs = mc.run_campaign(workers=2, **kw)
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=50
    ) as cluster:
        on_dask = mc.run_campaign(scheduler=cluster.scheduler_address, **kw)
    assert serial.task_function == "experiments.ablation:ablation_task"
    _same(serial.tasks, procs.tasks)
    _same(serial.tasks, on_dask.tasks)


def test_runner_does_not_import_the_experiments_and_resolves_registered_tasks():
    """Issue 12 item 5: the arrow runs one way (ablation -> montecarlo). The runner module
    imports no experiment module; tasks come as callables or registry names."""
    import ast
    import inspect

    tree = ast.parse(inspect.getsource(mc))
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            imported.add(node.module)
        elif isinstance(node, ast.Import):
            imported.update(a.name for a in node.names)
    assert not any(m.startswith("experiments.") and m != "experiments.registry" for m in imported), imported
    from experiments.ablation import ablation_task

    assert mc.resolve_task("ablation") is ablation_task
    assert mc.resolve_task(None) is ablation_task
    assert mc.resolve_task(static_bias_task) is static_bias_task
    with pytest.raises(GyroInputError, match="unknown Monte Carlo task"):
        mc.resolve_task("no_such_task")


def _fail_or_sleep(task):
    """Task 0 fails at once, the others would run for 10 minutes."""
    import time

    if task.index == 0:
        raise RuntimeError("task 0 fails")
    time.sleep(600)


def test_a_failed_task_ends_the_running_ones_at_once():
    """The failure reaches the caller without waiting for the running tasks (they are ended):
    what lets `gyroharness run` keep its finished sections promptly on an error or a Ctrl-C."""
    import time

    tasks = mc.make_tasks(scenarios=("static",), sensors=("icm42688p",), instances=2, seed=0)
    t0 = time.monotonic()
    with pytest.raises(RuntimeError, match="task 0 fails"):
        mc.execute(_fail_or_sleep, tasks, workers=2)
    # the sleeping task would hold the pool's shutdown for 600 s; ending it takes the spawn
    # start-up of two interpreters at most (seconds even on a loaded machine)
    assert time.monotonic() - t0 < 300
