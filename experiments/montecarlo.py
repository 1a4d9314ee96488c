"""Monte Carlo campaigns: many sensor instances × scenarios, on local cores or a Dask cluster.

A campaign is a list of tasks ``(scenario, sensor, instance)``. Each task is run by a
module-level *task function* (picklable, so it travels to worker processes and Dask workers)
that returns a small frozen :class:`TaskResult` (named scalar metrics), given as a callable or
as a name registered in :data:`experiments.registry.TASKS` (default ``"ablation"``:
:func:`experiments.ablation.ablation_task`, one instance through the ablation: attitude error
with no correction, each correction, all of them, and the noise floor). The runner never
imports an experiment module: the experiments import the runner, one way. The results are
aggregated per (scenario, sensor) into median / p90 tables written atomically as JSON, CSV
and Markdown, which the ablation report reads back with :func:`read_campaign`.

Seeding
-------
Instance ``i`` draws every random number from the ``i``-th child of
``np.random.SeedSequence(seed).spawn(instances)``, reduced to a 32-bit integer seed
(:func:`instance_seeds`), so that one instance can be reproduced alone with
``gyroharness simulate SCENARIO --sensor P --seed <task seed>``. The same instance seed is
used for every scenario and sensor: instance ``i`` is "the same physical part" in every
scenario, and comparisons between scenarios or corrections are paired (common random
numbers). Because a task's seed depends only on (campaign seed, instance), the results are
bit-identical whatever the backend (serial, local processes, Dask) and worker count, and
whatever subset of scenarios or sensors is selected.

Backends
--------
* ``workers=1`` and no scheduler: serial, in this process.
* ``workers=K > 1``: :class:`concurrent.futures.ProcessPoolExecutor` with the ``spawn``
  start method (safe with threads, MuJoCo and a live Dask client in the parent; a script
  that starts such a campaign needs the usual ``if __name__ == "__main__":`` guard).
* ``scheduler="tcp://host:port"``: an existing Dask distributed cluster through
  ``dask.distributed.Client(address)``.
"""

from __future__ import annotations

import csv
import io
import json
import math
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from gyrocore.data.jsonable import to_jsonable
from gyrocore.fleet import worker_environment
from gyrocore.errors import GyroInputError
from gyrocore.data.recording import atomic_write_text
from experiments.registry import get_task
from sim.presets import PRESETS
from sim.scenarios import SCENARIOS

__all__ = [
    "FORMAT_VERSION",
    "MonteCarloTask",
    "TaskResult",
    "MetricSummary",
    "CampaignResult",
    "instance_seeds",
    "make_tasks",
    "execute",
    "summarise",
    "run_campaign",
    "write_campaign",
    "read_campaign",
    "campaign_markdown",
    "default_workers",
    "resolve_task",
    "DEFAULT_TASK",
    "resolve_names",
    "to_jsonable_summary",
]

FORMAT_VERSION = "1.0"
#: Percentile reported beside the median (numpy's default linear interpolation).
P_HIGH = 90.0


# ---------------------------------------------------------------------------- data types
@dataclass(frozen=True)
class MonteCarloTask:
    """One unit of work: a scenario run by one instance of one sensor.

    Parameters
    ----------
    index : int
        Position in the campaign (results are returned in this order).
    scenario : str
        Scenario name (``sim.scenarios.SCENARIOS``).
    sensor : str
        Sensor preset name or TOML path (``sim.presets``).
    instance : int
        Instance number, 0-based.
    seed : int
        32-bit seed of this instance (:func:`instance_seeds`).
    duration_s : float or None
        Scenario duration, s (None: the scenario's default).
    options : tuple of (str, object)
        Extra keyword options for the task function (hashable, picklable).
    """

    index: int
    scenario: str
    sensor: str
    instance: int
    seed: int
    duration_s: float | None = None
    options: tuple[tuple[str, Any], ...] = ()


@dataclass(frozen=True)
class TaskResult:
    """The small frozen result of one task.

    Parameters
    ----------
    index, scenario, sensor, instance, seed
        Copied from the :class:`MonteCarloTask`.
    metrics : tuple of (str, float)
        Named scalar results in SI or datasheet units named in the metric name
        (e.g. ``att_err_final_all_deg``). NaN where a metric does not apply.
    """

    index: int
    scenario: str
    sensor: str
    instance: int
    seed: int
    metrics: tuple[tuple[str, float], ...]

    @property
    def metrics_dict(self) -> dict[str, float]:
        """The metrics as an ordered dict."""
        return dict(self.metrics)

    @classmethod
    def from_task(cls, task: MonteCarloTask, metrics: Mapping[str, float]) -> "TaskResult":
        """Build the result of ``task`` from a ``{name: value}`` mapping (order kept)."""
        return cls(
            index=task.index,
            scenario=task.scenario,
            sensor=task.sensor,
            instance=task.instance,
            seed=task.seed,
            metrics=tuple((str(k), float(v)) for k, v in metrics.items()),
        )


@dataclass(frozen=True)
class MetricSummary:
    """Distribution of one metric over the instances of one (scenario, sensor).

    ``n`` counts the finite values; the statistics ignore NaN. ``p90`` is numpy's
    ``percentile(x, 90)`` with linear interpolation; ``std`` uses ddof=1.
    """

    scenario: str
    sensor: str
    metric: str
    n: int
    median: float
    p90: float
    mean: float
    std: float


@dataclass(frozen=True)
class CampaignResult:
    """A whole campaign: configuration, per-task results and summary table.

    ``wall_s`` (elapsed time of :func:`execute`) and ``backend``/``workers`` describe the run,
    not the results: two runs with the same seed have identical ``tasks`` and ``summary``.
    """

    format_version: str
    task_function: str
    seed: int
    scenarios: tuple[str, ...]
    sensors: tuple[str, ...]
    instances: int
    duration_s: float | None
    backend: str
    workers: int
    wall_s: float
    tasks: tuple[TaskResult, ...]
    summary: tuple[MetricSummary, ...]
    options: tuple[tuple[str, Any], ...] = field(default=())

    def table(self, metric: str) -> dict[tuple[str, str], MetricSummary]:
        """``{(scenario, sensor): MetricSummary}`` of one metric."""
        return {(s.scenario, s.sensor): s for s in self.summary if s.metric == metric}

    @property
    def metric_names(self) -> tuple[str, ...]:
        """Metric names in first-seen order."""
        seen: dict[str, None] = {}
        for r in self.tasks:
            for k, _ in r.metrics:
                seen.setdefault(k, None)
        return tuple(seen)


# ---------------------------------------------------------------------------- tasks
def instance_seeds(seed: int, instances: int) -> list[int]:
    """32-bit seeds of instances ``0..instances-1``.

    Instance ``i`` gets ``SeedSequence(seed).spawn(instances)[i].generate_state(1)[0]``;
    spawned children depend only on (seed, i), so the seed of instance ``i`` does not change
    when the number of instances does.
    """
    if instances < 1:
        raise GyroInputError(f"instances must be >= 1, got {instances}")
    if seed < 0:
        raise GyroInputError(f"seed must be >= 0, got {seed}")
    children = np.random.SeedSequence(seed).spawn(instances)
    return [int(c.generate_state(1, dtype=np.uint32)[0]) for c in children]


def make_tasks(
    *,
    scenarios: Sequence[str],
    sensors: Sequence[str],
    instances: int,
    seed: int,
    duration_s: float | None = None,
    options: Mapping[str, Any] | None = None,
) -> list[MonteCarloTask]:
    """All (scenario, sensor, instance) tasks, scenario-major, with their seeds."""
    if not scenarios:
        raise GyroInputError("no scenarios given")
    if not sensors:
        raise GyroInputError("no sensors given")
    if duration_s is not None and not (math.isfinite(duration_s) and duration_s > 0):
        raise GyroInputError(f"duration must be a positive number of seconds, got {duration_s}")
    seeds = instance_seeds(seed, instances)
    opts = tuple(sorted((options or {}).items()))
    tasks = []
    for sc in scenarios:
        for se in sensors:
            for i, s in enumerate(seeds):
                tasks.append(MonteCarloTask(len(tasks), sc, se, i, s, duration_s, opts))
    return tasks


#: Registry name of the default task (:data:`experiments.registry.TASKS`).
DEFAULT_TASK = "ablation"


def resolve_task(task: Callable[[MonteCarloTask], TaskResult] | str | None) -> Callable[[MonteCarloTask], TaskResult]:
    """A task callable from a callable, a registered task name, or None (:data:`DEFAULT_TASK`)."""
    if task is None:
        task = DEFAULT_TASK
    if isinstance(task, str):
        return get_task(task)
    if not callable(task):
        raise GyroInputError(f"task_function must be callable or a registered task name, got {task!r}")
    return task


def default_workers() -> int:
    """Cores this process may use (``os.sched_getaffinity``)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


def _function_name(fn: Callable) -> str:
    return f"{getattr(fn, '__module__', '?')}:{getattr(fn, '__qualname__', repr(fn))}"


def execute(
    fn: Callable[[MonteCarloTask], TaskResult],
    tasks: Sequence[MonteCarloTask],
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool | Callable[[int, int], None] = False,
    connect_timeout_s: float = 10.0,
) -> tuple[list[TaskResult], str, int]:
    """Run ``fn`` on every task; results in task order.

    Parameters
    ----------
    fn : callable
        Module-level function ``MonteCarloTask -> TaskResult`` (pickled by reference for
        local processes, by cloudpickle for Dask).
    tasks : sequence of MonteCarloTask
    workers : int or None
        Local worker processes (None: :func:`default_workers`; 1: serial in this process).
        Ignored when ``scheduler`` is given (the cluster has its own workers).
    scheduler : str or None
        Address of a running Dask scheduler, e.g. ``tcp://10.0.0.5:8786``.
    progress : bool or callable
        True: show a tqdm bar on stderr; a callable ``(done, total)`` is called as tasks finish.
    connect_timeout_s : float
        How long to try to reach the Dask scheduler, s.

    Returns
    -------
    results : list of TaskResult
    backend : str
        ``"serial"``, ``"processes"`` or ``"dask"``.
    workers : int
        Workers actually used (for Dask: the cluster's worker count at submission).
    """
    tasks = list(tasks)
    bar = None
    done = [0]
    if progress and not callable(progress):
        from tqdm import tqdm

        bar = tqdm(total=len(tasks), unit="task", desc="montecarlo", leave=False)

    def tick(r):
        done[0] += 1
        if bar is not None:
            bar.update(1)
        elif callable(progress):
            progress(done[0], len(tasks))
        return r

    try:
        if scheduler is not None:
            results, n_workers = _execute_dask(fn, tasks, scheduler, tick, connect_timeout_s)
            backend = "dask"
        else:
            n_workers = default_workers() if workers is None else int(workers)
            if n_workers < 1:
                raise GyroInputError(f"workers must be >= 1, got {n_workers}")
            n_workers = min(n_workers, max(1, len(tasks)))
            if n_workers == 1:
                results = [tick(fn(t)) for t in tasks]
                backend = "serial"
            else:
                ctx = multiprocessing.get_context("spawn")
                try:
                    with ProcessPoolExecutor(max_workers=n_workers, mp_context=ctx) as pool:
                        # Workers are spawned (fresh interpreters) during the submissions and
                        # read the BLAS/OpenMP thread counts from the environment at start-up.
                        with worker_environment():
                            futures = [pool.submit(fn, t) for t in tasks]
                        try:
                            results = [tick(f.result()) for f in futures]
                        except BaseException:
                            stop_pool(pool, futures)
                            raise
                except BrokenProcessPool:
                    raise RuntimeError(
                        "a Monte Carlo worker process died (out of memory?, or a script that starts a "
                        "campaign with workers > 1 without an `if __name__ == '__main__':` guard)"
                    ) from None
                backend = "processes"
    finally:
        if bar is not None:
            bar.close()
    for t, r in zip(tasks, results):
        if not isinstance(r, TaskResult) or r.index != t.index:
            raise RuntimeError(f"task function {_function_name(fn)} returned a wrong result for task {t.index}")
    return results, backend, n_workers


def stop_pool(pool, futures) -> None:
    """Cancel the pending tasks and end the running ones of a local process pool at once.

    On Ctrl-C or a failed task the pool's ``shutdown(wait=True)`` (the ``with`` block's exit)
    would otherwise wait for every running task (minutes for a long flight) before the error
    or the interrupt reaches the caller; ``gyroharness run`` keeps the finished sections.
    """
    for f in futures:
        f.cancel()
    for proc in list((getattr(pool, "_processes", None) or {}).values()):
        if proc.is_alive():
            proc.terminate()


def _execute_dask(fn, tasks, address, tick, timeout_s):
    from dask.distributed import Client, as_completed

    try:
        client = Client(address, timeout=f"{timeout_s}s", set_as_default=False)
    except (OSError, TimeoutError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise GyroInputError(f"cannot connect to the Dask scheduler at {address}: {msg}") from None
    with client:
        n_workers = len(client.scheduler_info().get("workers", {}))
        futures = client.map(fn, tasks, pure=False)
        index = {f.key: i for i, f in enumerate(futures)}
        results: list[TaskResult | None] = [None] * len(tasks)
        for fut in as_completed(futures, loop=client.loop):
            results[index[fut.key]] = tick(fut.result())
    return results, n_workers


def resolve_names(*, scenarios: Sequence[str] | None, sensors: Sequence[str] | None) -> tuple[list[str], list[str]]:
    """Check scenario and sensor names against the simulator's registries.

    ``None`` means all of them (``sim.scenarios.SCENARIOS``, ``sim.presets.PRESETS``). A sensor
    may also be a path to a TOML preset file. Unknown names -> one-line :class:`GyroInputError`.
    """
    scen = list(SCENARIOS) if scenarios is None else [s.strip() for s in scenarios if s.strip()]
    sens = list(PRESETS) if sensors is None else [s.strip() for s in sensors if s.strip()]
    bad = [s for s in scen if s not in SCENARIOS]
    if bad:
        raise GyroInputError(f"unknown scenario(s) {', '.join(bad)}; known: {', '.join(SCENARIOS)}")
    bad = [s for s in sens if s not in PRESETS and not (s.endswith(".toml") and Path(s).is_file())]
    if bad:
        raise GyroInputError(f"unknown sensor(s) {', '.join(bad)}; known: {', '.join(PRESETS)} (or a .toml file)")
    if not scen or not sens:
        raise GyroInputError("no scenarios or no sensors to run")
    return scen, sens


def to_jsonable_summary(s: MetricSummary) -> dict:
    """One summary row as a JSON-ready dict (NaN -> None)."""
    return to_jsonable(s)


# ---------------------------------------------------------------------------- summary
def summarise(results: Iterable[TaskResult]) -> tuple[MetricSummary, ...]:
    """Median, p90, mean and std of every metric per (scenario, sensor), NaN ignored."""
    groups: dict[tuple[str, str], dict[str, list[float]]] = {}
    for r in results:
        g = groups.setdefault((r.scenario, r.sensor), {})
        for k, v in r.metrics:
            g.setdefault(k, []).append(v)
    out = []
    for (sc, se), metrics in groups.items():
        for name, values in metrics.items():
            x = np.asarray(values, float)
            x = x[np.isfinite(x)]
            n = int(x.size)
            out.append(
                MetricSummary(
                    scenario=sc,
                    sensor=se,
                    metric=name,
                    n=n,
                    median=float(np.median(x)) if n else math.nan,
                    p90=float(np.percentile(x, P_HIGH)) if n else math.nan,
                    mean=float(np.mean(x)) if n else math.nan,
                    std=float(np.std(x, ddof=1)) if n > 1 else math.nan,
                )
            )
    return tuple(out)


def run_campaign(
    *,
    scenarios: Sequence[str],
    sensors: Sequence[str],
    instances: int,
    seed: int = 0,
    duration_s: float | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    task_function: Callable[[MonteCarloTask], TaskResult] | str | None = None,
    options: Mapping[str, Any] | None = None,
    progress: bool | Callable[[int, int], None] = False,
) -> CampaignResult:
    """Build the tasks, run them (serial / local processes / Dask) and summarise.

    ``task_function`` is a module-level callable or a name of :data:`experiments.registry.TASKS`
    (None: :data:`DEFAULT_TASK`, the ablation: simulate the scenario with one sensor instance,
    calibrate it, score the attitude error of every correction row against the truth).
    """
    task_function = resolve_task(task_function)
    tasks = make_tasks(
        scenarios=scenarios,
        sensors=sensors,
        instances=instances,
        seed=seed,
        duration_s=duration_s,
        options=options,
    )
    t0 = time.perf_counter()
    results, backend, n_workers = execute(task_function, tasks, workers=workers, scheduler=scheduler, progress=progress)
    wall_s = time.perf_counter() - t0
    return CampaignResult(
        format_version=FORMAT_VERSION,
        task_function=_function_name(task_function),
        seed=int(seed),
        scenarios=tuple(scenarios),
        sensors=tuple(sensors),
        instances=int(instances),
        duration_s=duration_s,
        backend=backend,
        workers=n_workers,
        wall_s=wall_s,
        tasks=tuple(results),
        summary=summarise(results),
        options=tuple(sorted((options or {}).items())),
    )


# ---------------------------------------------------------------------------- files
JSON_NAME = "montecarlo.json"
TASKS_CSV_NAME = "montecarlo_tasks.csv"
SUMMARY_CSV_NAME = "montecarlo_summary.csv"
MARKDOWN_NAME = "montecarlo.md"


def _fmt(v: float) -> str:
    if v is None or not math.isfinite(v):
        return "—"
    return f"{v:.4g}"


def campaign_markdown(result: CampaignResult) -> str:
    """Markdown report: one table per scenario, a row per metric, median / p90 per sensor."""
    lines = [
        "# Monte Carlo campaign",
        "",
        f"{result.instances} instance(s) × {len(result.sensors)} sensor(s) × "
        f"{len(result.scenarios)} scenario(s), seed {result.seed}, "
        f"duration {'scenario default' if result.duration_s is None else f'{result.duration_s:g} s'}; "
        f"backend {result.backend} with {result.workers} worker(s), {result.wall_s:.1f} s wall.",
        f"Task function `{result.task_function}`. Cells: median / p{P_HIGH:g} over instances "
        "(NaN excluded; n is the count of finite values).",
        "",
    ]
    for sc in result.scenarios:
        rows = [s for s in result.summary if s.scenario == sc]
        if not rows:
            continue
        lines += [f"## {sc}", ""]
        head = "| metric | " + " | ".join(f"{se} (n)" for se in result.sensors) + " |"
        lines += [head, "|---|" + "---|" * len(result.sensors)]
        by = {(s.sensor, s.metric): s for s in rows}
        metrics: dict[str, None] = {}
        for s in rows:
            metrics.setdefault(s.metric, None)
        for m in metrics:
            cells = []
            for se in result.sensors:
                s = by.get((se, m))
                cells.append("—" if s is None else f"{_fmt(s.median)} / {_fmt(s.p90)} ({s.n})")
            lines.append(f"| `{m}` | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def _csv_text(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for row in rows:
        w.writerow(
            ["nan" if isinstance(v, float) and math.isnan(v) else (repr(v) if isinstance(v, float) else v) for v in row]
        )
    return buf.getvalue()


def write_campaign(result: CampaignResult, out_dir: str | os.PathLike) -> dict[str, Path]:
    """Write the campaign atomically: JSON (everything), two CSVs and a Markdown report.

    Returns ``{"json": path, "tasks_csv": path, "summary_csv": path, "markdown": path}``.
    Floats in the CSVs are written with ``repr`` (shortest round-trip form).
    """
    out = Path(out_dir)
    paths = {
        "json": out / JSON_NAME,
        "tasks_csv": out / TASKS_CSV_NAME,
        "summary_csv": out / SUMMARY_CSV_NAME,
        "markdown": out / MARKDOWN_NAME,
    }
    names = list(result.metric_names)
    task_rows = []
    for r in result.tasks:
        m = r.metrics_dict
        task_rows.append([r.scenario, r.sensor, r.instance, r.seed, *[m.get(k, math.nan) for k in names]])
    atomic_write_text(paths["tasks_csv"], _csv_text(["scenario", "sensor", "instance", "seed", *names], task_rows))
    atomic_write_text(
        paths["summary_csv"],
        _csv_text(
            ["scenario", "sensor", "metric", "n", "median", f"p{P_HIGH:g}", "mean", "std"],
            ([s.scenario, s.sensor, s.metric, s.n, s.median, s.p90, s.mean, s.std] for s in result.summary),
        ),
    )
    doc = to_jsonable(result)
    doc["tasks"] = [
        {
            **{k: getattr(r, k) for k in ("index", "scenario", "sensor", "instance", "seed")},
            "metrics": {k: to_jsonable(v) for k, v in r.metrics},
        }
        for r in result.tasks
    ]
    doc["options"] = {k: to_jsonable(v) for k, v in result.options}
    atomic_write_text(paths["json"], json.dumps(doc, indent=1, allow_nan=False) + "\n")
    atomic_write_text(paths["markdown"], campaign_markdown(result) + "\n")
    return paths


def _f(v) -> float:
    return math.nan if v is None else float(v)


def read_campaign(path: str | os.PathLike) -> CampaignResult:
    """Read ``montecarlo.json`` (or the folder holding it) back into a :class:`CampaignResult`."""
    p = Path(path)
    if p.is_dir():
        p = p / JSON_NAME
    if not p.is_file():
        raise GyroInputError(f"{p}: no such Monte Carlo result file")
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise GyroInputError(f"{p}: not a Monte Carlo JSON file ({str(exc).splitlines()[0]})") from None
    ver = str(doc.get("format_version", ""))
    if ver.split(".")[0] != FORMAT_VERSION.split(".")[0]:
        raise GyroInputError(f"{p}: format_version {ver or '?'} is not readable by this version ({FORMAT_VERSION})")
    try:
        tasks = tuple(
            TaskResult(
                index=int(t["index"]),
                scenario=t["scenario"],
                sensor=t["sensor"],
                instance=int(t["instance"]),
                seed=int(t["seed"]),
                metrics=tuple((k, _f(v)) for k, v in t["metrics"].items()),
            )
            for t in doc["tasks"]
        )
        summary = tuple(
            MetricSummary(
                scenario=s["scenario"],
                sensor=s["sensor"],
                metric=s["metric"],
                n=int(s["n"]),
                median=_f(s["median"]),
                p90=_f(s["p90"]),
                mean=_f(s["mean"]),
                std=_f(s["std"]),
            )
            for s in doc["summary"]
        )
        return CampaignResult(
            format_version=ver,
            task_function=doc["task_function"],
            seed=int(doc["seed"]),
            scenarios=tuple(doc["scenarios"]),
            sensors=tuple(doc["sensors"]),
            instances=int(doc["instances"]),
            duration_s=None if doc["duration_s"] is None else float(doc["duration_s"]),
            backend=doc["backend"],
            workers=int(doc["workers"]),
            wall_s=float(doc["wall_s"]),
            tasks=tasks,
            summary=summary,
            options=tuple(sorted(doc.get("options", {}).items())),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise GyroInputError(f"{p}: malformed Monte Carlo result ({type(exc).__name__}: {exc})") from None
