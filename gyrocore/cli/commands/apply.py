"""``gyroharness apply``: remove fitted effects from a data file (CSV or Parquet), streaming."""

from __future__ import annotations

import math
import os
import warnings

import click
import numpy as np

from gyrocore.cli import emit_json

D = 180.0 / math.pi
#: Rows of context taken from each neighbouring chunk, so that every sample of a chunk is
#: corrected exactly as in the whole record (central differences, the time-offset shift).
CONTEXT_ROWS = 8


def _context_rows(res, first) -> int:
    """Neighbour rows a chunk needs: the time-offset shift reaches |τ|/dt samples away."""
    ctx = CONTEXT_ROWS
    if "time_offset" in res.params and first.n > 1:
        tau = abs(float(np.asarray(res.params["time_offset"]["tau_s"])))
        dt = float(np.min(np.diff(first.t_s)))
        ctx = max(ctx, int(math.ceil(tau / dt)) + 2) if dt > 0 else ctx
    if first.n > 1:  # the registry's own reach (e.g. a regressor of the rate derivative alpha_*)
        from gyrocore.effects.registry import context_rows

        dt = float(np.min(np.diff(first.t_s)))
        ctx = max(ctx, context_rows(res.params, dt)) if dt > 0 else ctx
    return ctx


def apply_streaming(res, path: str, output: str, *, power_up_bias: bool = False, rows: int = 200_000) -> dict:
    """Correct ``path`` chunk by chunk into ``output`` (atomic); bit-identical to
    ``res.apply`` on the whole record. Returns running statistics for the summary.

    Each chunk is corrected together with ``CONTEXT_ROWS`` rows of its neighbours (dropped
    afterwards) and with the time since power-up counted from the file's first sample, so
    the derivative and shift terms see the same neighbours as in the whole record. Memory:
    O(``rows``). The temperature-range warning is given once, for the whole file.
    """
    from gyrocore.errors import GyroInputError, warn_repair
    from gyrocore.data.recording import concat_recordings, iter_chunks, write_chunks

    if power_up_bias:  # (lazy: scipy.stats/optimize, ~40 MiB, only for the power-up bias)
        from gyrocore.calib.bias import startup_still_slice

    stats = {
        "n": 0,
        "s_corr": np.zeros(3),
        "s2_corr": np.zeros(3),
        "s2_before": np.zeros(3),
        "s2_after": np.zeros(3),
        "has_ref": None,
        "pub": None,
    }
    ranges = {
        e: (float(res.params[e]["temp_min_c"]), float(res.params[e]["temp_max_c"]))
        for e in ("bias_thermal", "scale_thermal")
        if e in res.params
    }
    n_out = {e: 0 for e in ranges}
    state = {"t0": None, "d": None}

    def corrected():
        it = iter(iter_chunks(path, rows=rows))
        prev_tail = None
        cur = next(it, None)
        if cur is None:
            return
        state["t0"] = float(cur.t_s[0])
        ctx = _context_rows(res, cur)
        while cur is not None:
            nxt = next(it, None)
            left = prev_tail.n if prev_tail is not None else 0
            window = concat_recordings([prev_tail, cur, None if nxt is None else nxt.slice(0, ctx)])
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                out = res.apply(window, t_since_power_up_s=window.t_s - state["t0"])
            for w in caught:  # the range warning is re-issued once for the file; others pass through
                if "outside the calibrated range" not in str(w.message):
                    warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
            out = out.slice(left, left + cur.n)
            if power_up_bias and state["d"] is None:  # from the file's still start (the first chunk)
                sl = startup_still_slice(out)
                if sl is None or sl.stop - sl.start < 8:
                    raise GyroInputError(
                        "power-up bias: the recording does not start still, so its bias cannot be re-estimated"
                    )
                state["d"] = out.gyro_rad_s[sl].mean(axis=0)
                stats["pub"] = (state["d"], sl.stop - sl.start)
            if state["d"] is not None:
                d = state["d"]
                out = out.with_gyro(
                    out.gyro_rad_s - d[None, :],
                    power_up_bias_rad_s=" ".join(f"{v:.6g}" for v in d),
                    power_up_bias_samples=str(stats["pub"][1]),
                )
            for e, (lo, hi) in ranges.items():
                n_out[e] += int(np.sum((cur.temp_c < lo) | (cur.temp_c > hi))) if cur.temp_c is not None else 0
            corr = cur.gyro_rad_s - out.gyro_rad_s
            stats["n"] += cur.n
            stats["s_corr"] += corr.sum(axis=0)
            stats["s2_corr"] += (corr * corr).sum(axis=0)
            stats["has_ref"] = cur.ref_rate_rad_s is not None
            if cur.ref_rate_rad_s is not None:
                stats["s2_before"] += ((cur.gyro_rad_s - cur.ref_rate_rad_s) ** 2).sum(axis=0)
                stats["s2_after"] += ((out.gyro_rad_s - cur.ref_rate_rad_s) ** 2).sum(axis=0)
            yield out
            prev_tail = cur.slice(max(cur.n - ctx, 0), cur.n)
            cur = nxt

    write_chunks(corrected(), output, overwrite=True)
    for e, (lo, hi) in ranges.items():
        if n_out[e]:
            warn_repair(
                f"{n_out[e]} of {stats['n']} samples have a temperature outside the calibrated range "
                f"{lo:.2f}..{hi:.2f} C; {e} is held at the range edge there"
            )
    return stats


@click.command("apply")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option(
    "--params", "params_path", required=True, type=click.Path(dir_okay=False), help="parameter file from calibrate"
)
@click.option(
    "-o",
    "--output",
    "output",
    required=True,
    type=click.Path(dir_okay=False),
    help="corrected data file to write (.parquet: Parquet, else CSV)",
)
@click.option(
    "--power-up-bias",
    is_flag=True,
    help="re-estimate the constant bias from FILE's still start (the bias changes at every power-up)",
)
@click.option(
    "--chunk-rows",
    type=click.IntRange(min=16),
    default=50_000,
    show_default=True,
    help="rows corrected at a time (memory O(chunk); the result does not depend on it)",
)
@click.option("--force", is_flag=True, help="overwrite an existing output file")
@click.option("--json", "as_json", is_flag=True, help="print JSON only")
def command(file, params_path, output, power_up_bias, chunk_rows, force, as_json):
    """Remove the effects in the parameter file from FILE's gyro and write the corrected file."""
    from gyrocore.errors import GyroInputError
    from gyrocore.calib.params import load_params

    if os.path.exists(output) and not force:
        raise GyroInputError(f"{output} exists; pass --force to overwrite it")
    if os.path.exists(file) and os.path.exists(output) and os.path.samefile(file, output):
        raise GyroInputError(f"{output}: output would overwrite the input")
    from gyrocore.readers.convert import detect_format

    fmt = detect_format(file)
    if fmt not in ("csv", "parquet"):
        # apply rewrites a data file row for row (its other columns copied): a source in another
        # format is converted first, so that what is corrected is the file the user keeps
        raise GyroInputError(
            f"{file}: a {fmt} recording, not a data file; convert it first: gyroharness convert {file} -o DATA.csv, "
            f"then apply DATA.csv"
        )
    res = load_params(params_path)
    st = apply_streaming(res, file, output, power_up_bias=power_up_bias, rows=chunk_rows)
    n = st["n"]
    summary = {
        "input": os.path.basename(file),
        "output": output,
        "effects": list(res.effects),
        "params_source": {"file": res.source_file, "sha256": res.source_sha256},
        "n_samples": n,
        "mean_correction_rad_s": st["s_corr"] / n,
        "rms_correction_rad_s": np.sqrt(st["s2_corr"] / n),
        "power_up_bias_rad_s": [float(x) for x in st["pub"][0]] if power_up_bias else None,
    }
    if st["has_ref"]:
        summary["rms_error_before_rad_s"] = np.sqrt(st["s2_before"] / n)
        summary["rms_error_after_rad_s"] = np.sqrt(st["s2_after"] / n)
    if as_json:
        emit_json(summary)
    else:
        click.echo(f"removed {', '.join(res.effects)} (fitted on {res.source_file}) from {n} samples -> {output}")
        if "rms_error_before_rad_s" in summary:
            f = lambda v: ", ".join(f"{x * D:.4g}" for x in v)  # noqa: E731
            click.echo(
                f"RMS error vs reference: before [{f(summary['rms_error_before_rad_s'])}] deg/s, "
                f"after [{f(summary['rms_error_after_rad_s'])}] deg/s"
            )
