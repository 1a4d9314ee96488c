"""``gyroharness vibration FILE``: the vibration a gyro sees in flight (DESIGN.md "Flight logs and vibration").

FILE: a data file, a blackbox log (.BBL/.BFL/.TXT) or any format ``convert`` reads. JSON:
``{"rate_hz", "signal", "filters_before", "rms_above_40hz_rad_s", "lines", "bands", ...}``
(:meth:`gyrocore.flight.vibration.VibrationResult.to_json`); ``-o SPEC`` writes the vibration spec
the simulator reads; ``--plot PNG`` the spectra per throttle band with the lines overlaid.
"""

from __future__ import annotations

import contextlib
import math
import os

import click

from gyrocore.cli import emit_json
from gyrocore.errors import GyroInputError, warn_repair


@click.command("vibration")
@click.argument("path", metavar="FILE", type=click.Path(path_type=str))
@click.option(
    "-o",
    "--output",
    "spec_out",
    default=None,
    type=click.Path(path_type=str),
    help="Write the vibration spec (JSON) the simulator reads.",
)
@click.option(
    "--plot",
    "plot",
    default=None,
    type=click.Path(path_type=str),
    help="PNG: PSD per throttle band ((deg/s)^2/Hz) and spectrogram, lines overlaid.",
)
@click.option(
    "--signal",
    "use",
    type=click.Choice(["auto", "prefilter", "gyro"]),
    default="auto",
    show_default=True,
    help="auto: the less-filtered gyro when the log carries it; gyro: the gyro columns (as flown).",
)
@click.option(
    "--no-undo",
    is_flag=True,
    default=False,
    help="Do not undo the firmware's static filters (analyse the signal as logged).",
)
@click.option(
    "--window-s", type=float, default=1.0, show_default=True, help="Hann window, s (resolution 1.5/window Hz)."
)
@click.option("--bands", "n_bands", type=int, default=8, show_default=True, help="Throttle bands (equal-count).")
@click.option("--t-from-s", type=float, default=None, help="Analyse only t >= this (e.g. after a simulated take-off).")
@click.option(
    "--t-to-s",
    type=float,
    default=None,
    help="Analyse only t < this (e.g. one half of a flight: build a spec on one part, compare on the other).",
)
@click.option(
    "--band-edges",
    default=None,
    metavar="E0,E1,...",
    help="Throttle band edges (increasing, motor-command fraction) instead of equal-count bands, e.g. another "
    "part's spec's edges.",
)
@click.option("--log-index", type=int, default=None, help="blackbox: only this log of the file.")
@click.option("--force", is_flag=True, default=False, help="Overwrite existing outputs.")
@click.option("--json", "as_json", is_flag=True, default=False, help="Print the JSON result on stdout.")
def command(
    path, spec_out, plot, use, no_undo, window_s, n_bands, t_from_s, t_to_s, band_edges, log_index, force, as_json
):
    """Vibration of a flight log or a simulated hover: spectra vs throttle, broadband level, lines and their laws."""
    from gyrocore.readers.convert import detect_format, load_any
    from gyrocore.data.recording import read_csv
    from gyrocore.flight.vibration import plot_vibration, write_spec

    for o in (spec_out, plot):
        if o and not force and os.path.exists(o):
            raise GyroInputError(f"{o} exists; pass --force to overwrite it")
    fmt = detect_format(path)
    if log_index is not None and fmt != "blackbox":
        raise GyroInputError("--log-index applies to blackbox logs only")
    if fmt == "blackbox":
        rec = load_any(path, format="blackbox", log_index=log_index)
    elif fmt == "csv":
        rec = read_csv(path)
    else:
        rec = load_any(path)
    if window_s <= 0 or not math.isfinite(window_s):
        raise GyroInputError("--window-s must be positive")
    if n_bands < 1:
        raise GyroInputError("--bands must be >= 1")
    edges = None
    if band_edges is not None:
        try:
            edges = [float(x) for x in band_edges.split(",") if x.strip()]
        except ValueError:
            raise GyroInputError(f"--band-edges must be a comma list of numbers, got {band_edges!r}") from None
    if t_from_s is not None and t_to_s is not None and not t_to_s > t_from_s:
        raise GyroInputError("--t-to-s must be after --t-from-s")
    with batch_hint(rec, path):
        res = _analyse(rec, use, no_undo, window_s, n_bands, t_from_s, t_to_s, edges)
    for w in res.warnings:
        warn_repair(w)
    out = res.to_json()
    out["file"] = path
    if spec_out:
        write_spec(res, spec_out, source=path, overwrite=True)
        out["spec"] = spec_out
    if plot:
        plot_vibration(res, plot, title=f"{os.path.basename(path)}: {res.signal} gyro")
        out["plot"] = plot
    if as_json:
        emit_json(out)
        return
    d = 180 / math.pi
    click.echo(f"{path}: {res.signal} gyro at {res.rate_hz:.1f} Hz ({res.source})")
    if res.filters_before:
        click.echo(
            "filters before: "
            + "; ".join(
                f"{s['kind']} {s['cutoff_hz']:g} Hz{' (undone)' if s.get('undone') else ''}" for s in res.filters_before
            )
        )
    r = res.rms_above_40hz_rad_s
    click.echo(
        "rms above 40 Hz (deg/s): "
        + ", ".join(f"{a} {r[a] * d:.2f}" for a in "xyz")
        + f"  [band {res.rms_band_hz[0]:g}-{res.rms_band_hz[1]:.0f} Hz]"
    )
    for ln in res.lines:
        click.echo(
            f"  line {ln['axis']} {ln['frequency_hz']:7.1f} Hz  {ln['amplitude_rad_s'] * d:6.2f} deg/s  follows {ln['follows']}"
            + (" (aliased)" if ln.get("aliased") else "")
        )
    for e in res.energy_bands[:5]:
        click.echo(
            f"  band {e['axis']} {e['edges_hz'][0]:5.0f}-{e['edges_hz'][1]:.0f} Hz (centre {e['centre_hz']:.1f}, extent "
            f"{e['extent_hz'][0]:.0f}-{e['extent_hz'][1]:.0f})  {e['rms_rad_s'] * d:6.2f} deg/s  "
            f"{100 * (e['share_of_power_above_40hz'] or 0.0):4.1f} % of rms power above 40 Hz  follows {e.get('follows')}"
            + (
                ""
                if e["level_reliable"]
                else f" ({100 * e['power_above_reliable_fraction']:.0f} % above the reliable limit)"
            )
        )
    for a, dv in res.dominant_vibration.items():
        click.echo(f"dominant {a}: {dv['kind']} at {dv['frequency_hz']:.1f} Hz")
    for n in res.notes:
        click.echo("note: " + n)


def _analyse(rec, use, no_undo, window_s, n_bands, t_from_s, t_to_s, edges):
    from gyrocore.flight.vibration import analyse

    return analyse(
        rec,
        use=use,
        undo=not no_undo,
        window_s=window_s,
        n_bands=n_bands,
        t_from_s=t_from_s,
        t_to_s=t_to_s,
        band_edges=edges,
    )


@contextlib.contextmanager
def batch_hint(rec, path):
    """An ArduPilot log read from its IMU messages (logged at tens of Hz) whose batch sampler holds
    the gyro at the sensor rate: an analysis that fails on the slow stream says how to read the
    fast one (the IMU stream's own advice, "a longer --window-s", cannot reach the motor lines)."""
    try:
        yield
    except GyroInputError as exc:
        m = rec.meta
        if (
            m.get("format") == "dataflash"
            and m.get("stream", "imu") != "batch"
            and float(m.get("batch_sampler_windows", 0) or 0) > 0
            and rec.rate_hz < 200.0
        ):
            raise GyroInputError(
                f"{exc} (the IMU messages are logged at {rec.rate_hz:.3g} Hz; the log's batch sampler holds the "
                f"gyro at the sensor rate: gyroharness convert {path} --stream batch -o isb.csv, then analyse "
                f"isb.csv with --window-s 0.15)"
            ) from None
        raise
