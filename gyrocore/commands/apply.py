"""``gyroharness apply``: remove fitted effects from a data file."""

from __future__ import annotations

import math
import os

import click
import numpy as np

from ..cli import emit_json

D = 180.0 / math.pi


@click.command("apply")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--params", "params_path", required=True, type=click.Path(dir_okay=False), help="parameter file from calibrate")
@click.option("-o", "--output", "output", required=True, type=click.Path(dir_okay=False), help="corrected data file to write")
@click.option("--power-up-bias", is_flag=True,
              help="re-estimate the constant bias from FILE's still start (the bias changes at every power-up)")
@click.option("--force", is_flag=True, help="overwrite an existing output file")
@click.option("--json", "as_json", is_flag=True, help="print JSON only")
def command(file, params_path, output, power_up_bias, force, as_json):
    """Remove the effects in the parameter file from FILE's gyro and write the corrected file."""
    from ..errors import GyroInputError
    from ..model import load_params
    from ..recording import read_csv, write_csv

    if os.path.exists(output) and not force:
        raise GyroInputError(f"{output} exists; pass --force to overwrite it")
    res = load_params(params_path)
    rec = read_csv(file)
    out = res.apply(rec, power_up_bias=power_up_bias)
    write_csv(out, output, overwrite=True)
    summary = {
        "input": os.path.basename(file),
        "output": output,
        "effects": list(res.effects),
        "params_source": {"file": res.source_file, "sha256": res.source_sha256},
        "n_samples": rec.n,
        "mean_correction_rad_s": np.mean(rec.gyro_rad_s - out.gyro_rad_s, axis=0),
        "rms_correction_rad_s": np.sqrt(np.mean((rec.gyro_rad_s - out.gyro_rad_s) ** 2, axis=0)),
        "power_up_bias_rad_s": [float(x) for x in out.meta["power_up_bias_rad_s"].split()] if power_up_bias else None,
    }
    if rec.ref_rate_rad_s is not None:
        summary["rms_error_before_rad_s"] = np.sqrt(np.mean((rec.gyro_rad_s - rec.ref_rate_rad_s) ** 2, axis=0))
        summary["rms_error_after_rad_s"] = np.sqrt(np.mean((out.gyro_rad_s - rec.ref_rate_rad_s) ** 2, axis=0))
    if as_json:
        emit_json(summary)
    else:
        click.echo(f"removed {', '.join(res.effects)} (fitted on {res.source_file}) from {rec.n} samples -> {output}")
        if "rms_error_before_rad_s" in summary:
            f = lambda v: ", ".join(f"{x * D:.4g}" for x in v)  # noqa: E731
            click.echo(f"RMS error vs reference: before [{f(summary['rms_error_before_rad_s'])}] deg/s, "
                       f"after [{f(summary['rms_error_after_rad_s'])}] deg/s")
