"""``gyroharness montecarlo``: many sensor instances × scenarios, on local cores or a Dask cluster."""

from __future__ import annotations

import click

from gyrocore.cli import emit_json
from gyrocore.errors import GyroInputError


#: Metrics shown on the terminal when present (the ablation's headline rows); all are in the files.
KEY_METRICS = ("none__rms_deg", "all__rms_deg", "true_params__rms_deg", "floor__rms_deg")


def _split(text: str | None) -> list[str] | None:
    if text is None:
        return None
    items = [s.strip() for s in text.split(",") if s.strip()]
    if not items:
        raise GyroInputError("empty list; give comma-separated names")
    if len(set(items)) != len(items):
        raise GyroInputError(f"duplicate names in '{text}'")
    return items


@click.command("montecarlo")
@click.option(
    "--scenarios",
    default=None,
    metavar="A,B",
    help="Comma-separated scenario names (default: every scenario of sim.scenarios).",
)
@click.option(
    "--sensors",
    default=None,
    metavar="P,Q",
    help="Comma-separated sensor presets or TOML files (default: every preset).",
)
@click.option(
    "--instances",
    type=int,
    default=10,
    show_default=True,
    help="Sensor instances (independent random draws) per scenario and sensor.",
)
@click.option(
    "--workers", type=int, default=None, help="Local worker processes (default: the cores of this machine; 1 = serial)."
)
@click.option(
    "--scheduler",
    default=None,
    metavar="ADDRESS",
    help="Run on an existing Dask distributed cluster, e.g. tcp://10.0.0.5:8786.",
)
@click.option(
    "--duration-s", type=float, default=None, help="Scenario duration in seconds (default: each scenario's own)."
)
@click.option(
    "--seed",
    type=int,
    default=0,
    show_default=True,
    help="Campaign seed; instance i uses SeedSequence(seed).spawn(instances)[i].",
)
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    default="out/montecarlo",
    show_default=True,
    help="Folder for montecarlo.{json,md} and the CSV tables.",
)
@click.option(
    "--quick", is_flag=True, help="Short calibration recordings (60 s) in each task: a smoke run, not a measurement."
)
@click.option(
    "--progress/--no-progress", default=None, help="Progress bar on stderr (default: when stderr is a terminal)."
)
@click.option(
    "--task",
    "task",
    default="ablation",
    show_default=True,
    metavar="NAME",
    help="Task run per instance: a name of experiments.registry.TASKS (the runner imports no experiment).",
)
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON on stdout.")
def command(
    scenarios, sensors, instances, workers, scheduler, duration_s, seed, out_dir, quick, progress, task, as_json
):
    """Monte Carlo campaign: simulate, calibrate and score many sensor instances.

    Each task simulates one scenario with one instance of one sensor, fits the corrections,
    and scores the attitude error with no correction, with all corrections and at the noise
    floor. Results are identical whatever --workers or --scheduler (seeds depend only on
    --seed and the instance number). Writes median / p90 tables per scenario and sensor.
    """
    import sys

    from experiments import montecarlo as mc

    if scheduler is not None and workers is not None:
        raise GyroInputError("--workers and --scheduler exclude each other (the Dask cluster has its own workers)")
    if workers is not None and workers < 1:
        raise GyroInputError(f"--workers must be >= 1, got {workers}")
    if instances < 1:
        raise GyroInputError(f"--instances must be >= 1, got {instances}")
    mc.resolve_task(task)  # an unknown task name: one error line before any work
    scen = _split(scenarios)
    sens = _split(sensors)
    scen, sens = mc.resolve_names(scenarios=scen, sensors=sens)
    if progress is None:
        progress = sys.stderr.isatty()
    result = mc.run_campaign(
        scenarios=scen,
        sensors=sens,
        instances=instances,
        seed=seed,
        duration_s=duration_s,
        workers=workers,
        scheduler=scheduler,
        progress=progress,
        task_function=task,
        options={"quick": True} if quick else None,
    )
    paths = mc.write_campaign(result, out_dir)
    if as_json:
        emit_json(
            {
                "backend": result.backend,
                "workers": result.workers,
                "wall_s": result.wall_s,
                "seed": result.seed,
                "instances": result.instances,
                "scenarios": list(result.scenarios),
                "sensors": list(result.sensors),
                "files": {k: str(v) for k, v in paths.items()},
                "summary": [mc.to_jsonable_summary(s) for s in result.summary],
            }
        )
    else:
        names = result.metric_names
        key = [m for m in KEY_METRICS if m in names] or list(names[:6])
        click.echo(
            f"{len(result.tasks)} tasks on {result.backend} ({result.workers} worker(s)) in {result.wall_s:.1f} s"
        )
        click.echo("median [p90] per scenario and sensor:")
        for sc in result.scenarios:
            for se in result.sensors:
                cells = []
                for m in key:
                    s = result.table(m).get((sc, se))
                    if s is not None:
                        cells.append(f"{m} {s.median:.4g} [{s.p90:.4g}]")
                click.echo(f"  {sc} / {se}: " + ", ".join(cells))
        click.echo(
            f"wrote {paths['markdown']} (all {len(names)} metrics), {paths['json']}, "
            f"{paths['summary_csv']}, {paths['tasks_csv']}"
        )
