"""``gyroharness experiment NAME``: run one experiment into a report folder."""

from __future__ import annotations


import click

from gyrocore.cli import emit_json

__all__ = ["command"]


@click.command("experiment")
@click.argument("name")
@click.option(
    "--out", "out_dir", default=None, type=click.Path(file_okay=False), help="Report folder (default: out/<NAME>)."
)
@click.option("--quick", is_flag=True, help="Smoke run: short recordings, few sensor instances.")
@click.option("--seeds", type=click.IntRange(min=1), default=None, help="Sensor instances per scenario.")
@click.option("--workers", type=click.IntRange(min=1), default=None, help="Worker processes (default: all cores).")
@click.option("--force", is_flag=True, help="Replace --out even if it is not a previous gyroharness report.")
@click.option(
    "--noise",
    "noise",
    default=None,
    type=click.Path(dir_okay=False),
    help="protocol only: the flight's noise model — a JSON of `gyroharness noise --json`, a parameter file "
    "with a noise_model, or a long still recording (CSV/Parquet) to identify it from "
    "(default: a simulated still recording of the design unit, 4x the flight).",
)
@click.option(
    "--firmware",
    type=click.Choice(["betaflight"]),
    default=None,
    help="cutoffs only: fly the grid with the firmware in the loop (lockstep SITL; `gyroharness firmware "
    "build` first), beside our controller's verdict on the same airframe.",
)
@click.option(
    "--vehicle",
    default=None,
    help="cutoffs --firmware: airframe (default racing5, Betaflight's defaults are a 5-inch tune).",
)
@click.option("--scheduler", default=None, help="cutoffs --firmware: a Dask scheduler address for the Monte Carlo.")
@click.option("--json", "as_json", is_flag=True, help="Print a JSON summary on stdout.")
def command(name, out_dir, quick, seeds, workers, force, noise, firmware, vehicle, scheduler, as_json):
    """Run one experiment NAME (see `gyroharness run --help`; names: article, ablation, cutoffs, close_the_loop,
    twin, protocol).

    Same folder policy as `gyroharness run`.
    """
    from experiments import registry
    from experiments.report import build_report
    from gyrocore.errors import GyroInputError

    run = registry.get(name)
    extra = {}
    if noise is not None:
        if name != "protocol":
            raise GyroInputError(f"--noise applies to the protocol experiment only, not {name}")
        from experiments.protocol import load_noise

        extra["noise"] = load_noise(noise)  # bad files fail here, before any simulation
    if firmware is not None or vehicle is not None or scheduler is not None:
        if name != "cutoffs" or firmware is None:
            raise GyroInputError("--firmware (with --vehicle, --scheduler) applies to the cutoffs experiment only")
        from sim.firmware.build import ensure_binary
        from sim.vehicles import get_vehicle

        extra["firmware"] = firmware
        if vehicle is not None:
            extra["vehicle"] = get_vehicle(vehicle).name
        if scheduler is not None:
            extra["scheduler"] = scheduler
        extra["binary"] = ensure_binary().binary  # a missing build is one error line before the report starts
    path, results = build_report(
        [(name, run)],
        out_dir or f"out/{name}",
        force=force,
        quick=quick,
        seeds=seeds,
        workers=workers,
        title=f"gyroharness experiment {name}",
        **extra,
    )
    r = results[0]
    if as_json:
        doc = {"out": str(path), "name": name, "wall_s": r.wall_s, "figures": list(r.figures), "summary": r.summary}
        if isinstance(r.summary, dict) and "scenarios" in r.summary:  # ablation: predicted drift per scenario
            doc["scenarios"] = r.summary["scenarios"]
        emit_json(doc)
    else:
        click.echo(f"{name}: {r.wall_s:.1f} s, {len(r.figures)} figures; report: {path / 'report.md'}")
        src = r.summary.get("noise_source") if isinstance(r.summary, dict) else None
        if src:  # protocol: say which noise model the flight's budget used
            click.echo(f"noise model: {src['label']}")
    return 0
