"""``gyroharness twin FILE``: a digital twin of a real sensor, compared with the real one."""

from __future__ import annotations

import json
from pathlib import Path

import click

from gyrocore.cli import emit_json
from gyrocore.errors import GyroInputError

__all__ = ["command"]


@click.command("twin")
@click.argument("file", type=click.Path(exists=False))
@click.option(
    "--params",
    "params_file",
    default=None,
    type=click.Path(dir_okay=False),
    help="Parameter file of the declared model (default: the residual loop identifies it).",
)
@click.option(
    "--segments",
    "segments_file",
    default=None,
    type=click.Path(dir_okay=False),
    help="Still / known-rotation segments file (gyrocore.data.segments.read_segments).",
)
@click.option(
    "--replicas",
    type=int,
    default=None,
    help="Number of replicas N (default 199: the smallest p-value 1/(N+1) must be below α/5).",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Root seed of the replicas (SeedSequence.spawn).")
@click.option("--no-close", is_flag=True, help="Only compare the twin as given; do not add what it lacks.")
@click.option(
    "-o",
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False),
    help="Folder for twin.json, twin.md and the plots.",
)
@click.option("--json", "as_json", is_flag=True, help="Print the JSON result on stdout.")
def command(file, params_file, segments_file, replicas, seed, no_close, out_dir, as_json):
    """Replay FILE's reference motion through the simulator with the sensor's identified
    parameters, N times, and compare the real error signal with the replicas' (ADEV, PSD,
    distribution, window autocorrelation; attitude references also the loop's window residual).
    """
    from experiments import twin as T
    from gyrocore.data.recording import atomic_write_text

    if not Path(file).exists():
        raise GyroInputError(f"{file}: no such file or folder")
    if seed < 0:
        raise GyroInputError(f"--seed must be >= 0, got {seed}")
    rec, segs = T.load_recording(file)
    if segments_file is not None:
        from gyrocore.data.segments import read_segments

        segs = read_segments(segments_file)
    n_rep = T.DEFAULT_REPLICAS if replicas is None else replicas
    r = T.twin(
        rec, segments=segs, params_file=params_file, n_replicas=n_rep, seed=seed, close=not no_close, file=str(file)
    )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figs = T.plot_twin(r, out)
    d = r.to_json()
    d["figures"] = figs
    from gyrocore.data.jsonable import to_jsonable

    atomic_write_text(out / "twin.json", json.dumps(to_jsonable(d), indent=2, allow_nan=False) + "\n")
    atomic_write_text(out / "twin.md", T.markdown(r, figs) + "\n")
    if as_json:
        emit_json(d)
    else:
        click.echo(T.summary_text(r))
        click.echo(f"wrote {out / 'twin.json'}, {out / 'twin.md'} and {len(figs)} plots")
    return 0
