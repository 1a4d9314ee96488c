"""``gyroharness convert``: turn a real set (or any data file) into the DESIGN.md data file."""

from __future__ import annotations

import os
import warnings

import click

from gyrocore.cli import emit_json
from gyrocore.readers.convert import FORMATS, concat_converted, load_with_segments
from gyrocore.data.segments import write_segments
from gyrocore.errors import GyroInputError, RepairWarning
from gyrocore.readers.large import is_large
from gyrocore.data.recording import PARQUET_SUFFIXES, file_sha256, iter_chunks, write_chunks, write_csv, write_parquet


@click.command("convert")
@click.argument("input_path", metavar="INPUT", type=click.Path(path_type=str))
@click.option(
    "-o",
    "--output",
    "output",
    required=True,
    type=click.Path(path_type=str),
    help="Output data file (DESIGN.md columns, SI): Parquet when it ends in .parquet/.pq, else CSV.",
)
@click.option(
    "--to",
    "to",
    type=click.Choice(["auto", "csv", "parquet"]),
    default="auto",
    show_default=True,
    help="Output format (auto: from the output name).",
)
@click.option(
    "--format",
    "fmt",
    type=click.Choice(FORMATS),
    default="auto",
    show_default=True,
    help="Source format (auto: from name and first bytes).",
)
@click.option(
    "--lsb-per-dps",
    type=float,
    default=None,
    help="Gyro sensitivity of a raw-LSB source, LSB per deg/s (default: the source's datasheet value).",
)
@click.option("--lsb-per-g", type=float, default=None, help="Accel sensitivity of a raw-LSB source, LSB per g.")
@click.option("--rate-hz", type=float, default=None, help="Sample rate for sources without timestamps, Hz.")
@click.option(
    "--retime/--no-retime",
    default=None,
    help="Replace bursty host timestamps by a uniform grid at the mean rate (default on for sunsided).",
)
@click.option(
    "--no-flip-x",
    is_flag=True,
    default=False,
    help="sunsided: keep the raw gyro X sign (default: negate it as its README documents).",
)
@click.option(
    "--sections",
    type=click.Path(path_type=str),
    default=None,
    help="imucal: section list JSON (default <stem>_list.json).",
)
@click.option(
    "--log-index",
    type=int,
    default=None,
    help="blackbox: read only this log of the file (1-based; default: every log, as segments).",
)
@click.option(
    "--gyro-instance",
    type=int,
    default=None,
    help="ulog: read sensor_gyro instance N (one of several gyros, before PX4's calibration) instead of "
    "sensor_combined (the selected gyro, calibrated).",
)
@click.option(
    "--stream",
    type=click.Choice(["imu", "batch"]),
    default=None,
    help="dataflash: imu = IMU messages (gyro as flown, logger rate); batch = the IMU batch sampler's raw gyro windows (ISBH/ISBD).",
)
@click.option(
    "--segments-out",
    type=click.Path(path_type=str),
    default=None,
    help="Write the known-rotation segments file (t_start_s,t_end_s,kind,angle_x_deg,angle_y_deg,angle_z_deg,label).",
)
@click.option(
    "--append",
    "append",
    multiple=True,
    type=click.Path(path_type=str),
    help="Another recording of the same session, joined after INPUT (repeatable; same options), "
    "e.g. the rotate-* runs about y and z after the one about x: one file and one segments file.",
)
@click.option(
    "--gap-s",
    type=float,
    default=None,
    help="Time gap inserted between joined recordings, s (default: one sample interval).",
)
@click.option(
    "--chunk-rows",
    type=int,
    default=50_000,
    show_default=True,
    help="Rows per chunk when a large data file is streamed (memory ~ 10 copies of a chunk).",
)
@click.option("--force", is_flag=True, default=False, help="Overwrite existing output files.")
@click.option("--json", "as_json", is_flag=True, default=False, help="Print a JSON summary on stdout.")
def command(
    input_path,
    output,
    to,
    fmt,
    lsb_per_dps,
    lsb_per_g,
    rate_hz,
    retime,
    no_flip_x,
    sections,
    log_index,
    gyro_instance,
    stream,
    segments_out,
    append,
    gap_s,
    chunk_rows,
    force,
    as_json,
):
    """Convert INPUT (Betaflight/INAV/Cleanflight blackbox .BBL/.BFL/.TXT, ArduPilot DataFlash .bin, PX4 .ulg, sunsided folder, tomisuarez2/imucal/x-io CSV, BROAD .hdf5,
    IMU-TK .mat, gnss-ins-sim folder, or a data file, CSV or Parquet) to the DESIGN.md data file
    (CSV, or Parquet with --to parquet or an output named .parquet)."""
    _check_outputs(output, segments_out, (input_path, *append), force=force)
    out_parquet = to == "parquet" or (to == "auto" and output.lower().endswith(PARQUET_SUFFIXES))
    out_fmt = "auto" if to == "auto" else to
    opts = dict(
        lsb_per_dps=lsb_per_dps,
        lsb_per_g=lsb_per_g,
        rate_hz=rate_hz,
        retime=retime,
        sections=sections,
        log_index=log_index,
        stream=stream,
        gyro_instance=gyro_instance,
    )
    if no_flip_x:
        opts["flip_gyro_x"] = False
    repairs: list[str] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RepairWarning)
        from gyrocore.readers.convert import detect_format

        actual = detect_format(input_path) if fmt == "auto" else fmt
        if actual in ("csv", "parquet") and is_large(input_path, "convert") and not retime and not append:
            summary = _convert_streamed(input_path, output, actual, out_fmt, opts, chunk_rows)
            segs = ()
        else:
            summary, segs = _convert_in_memory(
                input_path,
                output,
                actual,
                fmt,
                opts,
                append=append,
                gap_s=gap_s,
                out_parquet=out_parquet,
                segments_out=segments_out,
            )
    for w in caught:
        if issubclass(w.category, RepairWarning):
            repairs.append(str(w.message))
        warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    if segments_out:
        if not segs:
            raise GyroInputError(
                f"{input_path}: a streamed CSV has no known rotations; --segments-out needs a rotation session"
            )
        write_segments(segs, segments_out, overwrite=True)
        summary["segments_file"] = segments_out
    summary["warnings"] = repairs
    summary["sha256"] = file_sha256(output)
    if as_json:
        emit_json(summary)
    else:
        n = summary["n_samples"]
        extra = f", {len(segs)} segments -> {segments_out}" if segments_out else ""
        click.echo(f"{input_path} ({summary['format']}) -> {output}: {n} samples{extra}")


def _check_outputs(output: str, segments_out: str | None, inputs, *, force: bool) -> None:
    """One error line for an output that exists (without --force) or would overwrite an input."""
    outs = [output] + ([segments_out] if segments_out else [])
    for o in outs:
        if not force and os.path.exists(o):
            raise GyroInputError(f"{o} exists; pass --force to overwrite it")
    for i in inputs:
        if os.path.abspath(output) == os.path.abspath(i):
            raise GyroInputError(f"{output}: output would overwrite the input")


def _convert_streamed(input_path: str, output: str, actual: str, out_fmt: str, opts: dict, chunk_rows: int) -> dict:
    """A large data file copied chunk by chunk (bounded memory); its JSON summary."""
    unsupported = [k for k, v in opts.items() if v is not None and k != "retime"]
    if unsupported:
        raise GyroInputError(f"option --{unsupported[0].replace('_', '-')} does not apply to format {actual}")
    n = (
        write_chunks(iter_chunks(input_path, rows=chunk_rows), output, overwrite=True)
        if out_fmt == "auto"
        else (_write_chunks_as(out_fmt, iter_chunks(input_path, rows=chunk_rows), output))
    )
    return {
        "input": input_path,
        "format": actual,
        "output": output,
        "n_samples": n,
        "streamed": True,
        "chunk_rows": chunk_rows,
        "segments": 0,
    }


def _convert_in_memory(input_path, output, actual, fmt, opts, *, append, gap_s, out_parquet, segments_out):
    """Read INPUT (and any --append recordings, joined) and write the data file; returns its
    JSON summary and the known-rotation segments."""
    from gyrocore.readers.convert import detect_format

    conv = load_with_segments(input_path, format=actual, **opts)
    if append:
        conv = concat_converted(
            [conv] + [load_with_segments(a, format=fmt if fmt != "auto" else detect_format(a), **opts) for a in append],
            gap_s=gap_s,
        )
    rec, segs = conv.recording, conv.segments
    if segments_out and not segs:
        raise GyroInputError(
            f"{input_path}: this recording has no known rotations; --segments-out needs a rotation session"
        )
    (write_parquet if out_parquet else write_csv)(rec, output, overwrite=True)
    summary = {
        "input": input_path,
        "format": conv.format,
        "output": output,
        "n_samples": rec.n,
        "duration_s": rec.duration_s,
        "rate_hz": rec.rate_hz,
        "streamed": False,
        "columns": {
            "accel": rec.accel_m_s2 is not None,
            "temp": rec.temp_c is not None,
            "ref_rate": rec.ref_rate_rad_s is not None,
            "ref_quat": rec.ref_quat_wxyz is not None,
            "extra": sorted(rec.extra),
        },
        "meta": dict(rec.meta),
        "segments": len(segs),
    }
    return summary, segs


def _write_chunks_as(fmt: str, chunks, output: str) -> int:
    from gyrocore.data.recording import write_csv_chunks, write_parquet_chunks

    return (write_parquet_chunks if fmt == "parquet" else write_csv_chunks)(chunks, output, overwrite=True)
