"""``gyroharness batch COMMAND DIR|GLOB``: one analysis over many recordings, on Dask.

Runs ``bias``, ``allan``, ``calibrate`` or ``loop`` on every data file (CSV or Parquet) of a
folder or a glob, in local worker processes (a Dask ``LocalCluster``, one single-threaded
worker per core by default) or on a running cluster (``--scheduler tcp://HOST:8786``), and
writes

* one results table (CSV, or Parquet when its name ends in ``.parquet``), one row per file:
  ``file``, ``sha256`` of the input, ``command``, ``options``, every headline number of the
  command (SI units in the column names), ``warnings`` (the repairs made while reading),
  ``error`` (empty when the file succeeded) and ``outliers`` (the headline numbers in which
  the file is an outlier of the fleet);
* a summary plot (PNG): the fleet's distribution of each headline number, outliers in red
  and named.

A file that fails (unreadable, empty, deg/s labelled rad/s, too short, ...) is a row with
its one-line error; the others complete. Rerunning with the same table skips the files
whose input hash already has a result for the same command and options (failed rows are
retried). Exit status: the number of failed files, capped at :data:`MAX_EXIT` (0: all
succeeded); a usage error prints one ``error:`` line and exits 2, as every command.

Outliers: robust z-score ``0.6745·(x − median)/MAD`` of each headline number over the
fleet's successful rows, ``|z| > 3.5`` (Iglewicz & Hoaglin, *How to Detect and Handle
Outliers*, ASQC 1993: the modified z-score; 0.6745 = Φ⁻¹(0.75) makes MAD/0.6745 the
standard deviation of a normal sample, and 3.5 flags a normal sample's value with
probability ≈ 5e-4). Needs ≥ 5 successful files; a number with MAD = 0 flags nothing.
"""

from __future__ import annotations

from pathlib import Path

import click

from gyrocore.cli import emit_json
from gyrocore.errors import GyroInputError
from gyrocore.fleet import COMMANDS, MAX_EXIT, default_workers, find_inputs, run_batch


@click.command("batch")
@click.argument("command_name", metavar="COMMAND", type=click.Choice(COMMANDS))
@click.argument("inputs", metavar="DIR|GLOB")
@click.option(
    "-o",
    "--output",
    "table",
    default=None,
    type=click.Path(dir_okay=False),
    help="results table (.csv, or .parquet); default batch_COMMAND.csv here. Rerunning with the same "
    "table skips files whose input hash already has a result",
)
@click.option(
    "--plot",
    "plot",
    default=None,
    type=click.Path(dir_okay=False),
    help="summary plot (PNG); default: the table's name with .png",
)
@click.option("--no-plot", is_flag=True, help="write no plot")
@click.option(
    "--effects", default="bias", show_default=True, help="calibrate: the effects to fit; loop: the declared effects"
)
@click.option(
    "--params-dir",
    type=click.Path(file_okay=False),
    default=None,
    help="calibrate: also write each file's parameter file here",
)
@click.option(
    "--workers",
    type=click.IntRange(min=0),
    default=None,
    help="local worker processes (default: one per core; 0: in this process, no Dask)",
)
@click.option("--scheduler", default=None, metavar="ADDRESS", help="a running Dask scheduler, e.g. tcp://host:8786")
@click.option("--no-resume", is_flag=True, help="rerun every file even if the table has its result")
@click.option("--progress/--no-progress", default=None, help="progress bar on stderr (default: when a terminal)")
@click.option("--json", "as_json", is_flag=True, help="print the JSON summary only")
@click.pass_context
def command(
    ctx,
    command_name,
    inputs,
    table,
    plot,
    no_plot,
    effects,
    params_dir,
    workers,
    scheduler,
    no_resume,
    progress,
    as_json,
):
    """Run COMMAND (bias, allan, calibrate, loop) on every data file of DIR (or matching GLOB);
    one results table and a fleet summary plot. Exit status: the number of failed files
    (at most 100)."""
    import sys

    from gyrocore.effects.registry import check_effect_names

    files = find_inputs(inputs)
    table = table or f"batch_{command_name}.csv"
    if not table.lower().endswith((".csv", ".parquet", ".pq")):
        raise GyroInputError(f"{table}: the results table must end in .csv or .parquet")
    if plot is None and not no_plot:
        plot = str(Path(table).with_suffix(".png"))
    if no_plot:
        plot = None
    options: dict = {}
    if command_name in ("calibrate", "loop"):
        options["effects"] = ",".join(check_effect_names([e.strip() for e in effects.split(",") if e.strip()]))
    if params_dir and command_name == "calibrate":
        Path(params_dir).mkdir(parents=True, exist_ok=True)
        options["params_dir"] = str(params_dir)
    if workers is None:
        workers = default_workers()
    summary = run_batch(
        command_name,
        files,
        table=table,
        plot=plot,
        options=options,
        workers=workers,
        scheduler=scheduler,
        resume=not no_resume,
        progress=sys.stderr.isatty() if progress is None else progress,
    )
    if as_json:
        emit_json(summary)
    else:
        click.echo(
            f"batch {command_name}: {summary['n_inputs']} files, {summary['n_run']} run, "
            f"{summary['n_skipped']} skipped (result in the table), {summary['n_failed']} failed "
            f"[{summary['backend']}, {summary['workers']} workers] -> {table}" + (f", {plot}" if plot else "")
        )
        for f in summary["failed"]:
            e = str(f["error"])
            click.echo(f"failed: {e}" if e.startswith(str(f["file"])) else f"failed: {f['file']}: {e}")
        for o in summary["outliers"]:
            click.echo(f"outlier: {o['file']}: {o['metric']} = {o['value']:.4g} (robust z {o['z']:+.1f})")
    ctx.exit(min(summary["n_failed"], MAX_EXIT))
