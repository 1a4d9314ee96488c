"""``gyroharness bias``: static (power-up) bias with a motion gate (the article's §1)."""

from __future__ import annotations

import math

import click
import numpy as np

from gyrocore.cli import emit_json
from gyrocore.readers.large import is_large

D = 180.0 / math.pi


def report_text(r) -> str:
    f = lambda v, s=D, p=5: "(" + ", ".join(f"{x * s:.{p}g}" for x in v) + ")"  # noqa: E731
    lines = [
        f"bias          {f(r.bias_rad_s)} deg/s  = {f(r.bias_rad_s, 1.0)} rad/s",
        f"std. error    {f(r.bias_se_rad_s, D, 3)} deg/s  (VIF {f(r.vif, 1.0, 3)})",
        f"rule          {r.rule}, gate statistic {r.statistic}",
        f"window        samples {r.window_start_index}..{r.window_start_index + r.window_samples - 1} "
        f"({r.window_start_s:.3f} s + {r.window_s:.3f} s); rejected before it: {r.n_rejected_windows}; "
        f"still windows {r.n_windows_still}/{r.n_windows_total}",
        f"threshold     {f(r.threshold, 1.0, 4)} {r.threshold_units}; false-reject rate at rest "
        + ("not derived (fixed threshold)" if not math.isfinite(r.false_reject_rate) else f"{r.false_reject_rate:g}"),
        f"noise sigma   {f(r.noise_sigma_rad_s, D, 3)} deg/s per sample",
        f"catches (50%) step {f(r.min_step_rad_s, D, 3)} deg/s, ramp {f(r.min_ramp_rad_s2, D, 3)} deg/s^2 "
        "(a constant rotation is indistinguishable from bias)",
    ]
    return "\n".join(lines)


@click.command("bias")
@click.argument("file", type=click.Path())  # a data file or any source `convert` reads (folders too)
@click.option("--rule", type=click.Choice(["mean", "median", "converge", "article"]), default="mean", show_default=True)
@click.option(
    "--statistic",
    type=click.Choice(["variance", "abs_diff"]),
    default="variance",
    show_default=True,
    help="motion-gate statistic (mean/median rules)",
)
@click.option("--window-s", type=float, default=None, help="window length, s (default 200 samples)")
@click.option("--window-samples", type=int, default=200, show_default=True)
@click.option(
    "--false-reject-rate",
    type=float,
    default=1e-3,
    show_default=True,
    help="probability that a still window is refused",
)
@click.option("--max-retries", type=int, default=None, help="windows to try after the first (default: all)")
@click.option(
    "--noise-dps", type=float, default=None, help="sensor white-noise sigma per sample, deg/s (default: from the data)"
)
@click.option("--lsb-dps", type=float, default=None, help="raw count size, deg/s (article rule; 1/131 at ±250 dps)")
@click.option("--article-counts", type=float, default=500.0, show_default=True, help="article rule threshold, counts")
@click.option("--json", "as_json", is_flag=True, help="print JSON only")
def command(
    file,
    rule,
    statistic,
    window_s,
    window_samples,
    false_reject_rate,
    max_retries,
    noise_dps,
    lsb_dps,
    article_counts,
    as_json,
):
    """Static bias of a still start, refusing windows with motion and retrying on the next."""
    from gyrocore.calib.bias import StaticBiasCalibrator

    cal = StaticBiasCalibrator(
        window_samples=window_samples,
        window_s=window_s,
        false_reject_rate=false_reject_rate,
        rule=rule,
        statistic=statistic,
        max_retries=max_retries,
        noise_sigma_rad_s=None if noise_dps is None else noise_dps / D,
        lsb_rad_s=None if lsb_dps is None else lsb_dps / D,
        article_threshold_counts=article_counts,
    )
    if is_large(file, "bias"):
        # a long file: t and gyro spilled to per-column files (every check and warning of a
        # whole read), then the gate and the estimate a block of windows / one column at a time
        import tempfile

        from gyrocore.data.spill import spill_columns

        with tempfile.TemporaryDirectory(prefix="gyroharness_bias_") as tmp:
            r = cal.fit(spill_columns(file, tmp))
    else:
        from gyrocore.readers.convert import read_any

        # a data file: t and gyro only (the gate and the estimate use nothing else); any other
        # source `convert` reads (a ULog, a blackbox, a tomisuarez2 CSV, ...) through its reader
        r = cal.fit(read_any(file, columns=()))
    from gyrocore.data.checks import STILL_NOISE_SUSPECT_RAD_S

    if noise_dps is None and np.any(np.asarray(r.noise_sigma_rad_s) > STILL_NOISE_SUSPECT_RAD_S):
        # the still windows' own noise: beyond any MEMS gyro at rest (the reader checks this only
        # when accel columns say the sensor is at rest)
        from gyrocore.errors import warn_repair

        warn_repair(
            f"the still window's per-sample noise ({', '.join(f'{v:.3g}' for v in r.noise_sigma_rad_s)}) rad/s exceeds "
            f"any MEMS gyro at rest ({STILL_NOISE_SUSPECT_RAD_S} rad/s per sample): is it deg/s labelled rad/s "
            f"(rename the columns gyro_*_deg_s)? The bias below is as read"
        )
    if as_json:
        emit_json(r)
    else:
        click.echo(report_text(r))
